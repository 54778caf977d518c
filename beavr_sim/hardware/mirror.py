"""Hardware mirroring, event-driven: every guarded command the twin applies goes to the devices.

The twin's thread calls :meth:`HardwareMirror.submit` with each action the moment it applies
it (already past the guard, :mod:`beavr_sim.twin.guard`): once per guarded command (one per
hand frame, at the headset's rate, with its jitter), and once per control period when no
command came in that period (a heartbeat with the same targets); with the twin's measured
joints. Each device has its own writer thread (a slow serial bus never slows the twin) that
sends the newest target and reads the measured joints back. The mirror:

- sends only what the twin's guard accepted: a command the twin refused never reaches a motor
  (the twin holds that effector, and so the device holds);
- limits every target it sends to the device's speed (:class:`~beavr_sim.twin.guard.GuardConfig`
  caps) over the time since the previous submit (at most one control period, at least
  :data:`MIN_INTERVAL_S`): commands bunched by scheduling jitter are slowed to the speed cap
  (``rate_limited``); when the twin is further away than one period's motion (after a hold, a
  release, a reset: :meth:`begin_episode`) the device *catches up* at the slower catch-up
  speed, whatever the submit rate, each intermediate target checked by the mirror's own copy
  of the guard (told each episode's fixtures) along its path;
- streams a device that wants a stream (:attr:`~beavr_sim.hardware.device.Device.stream_hz`)
  each target interpolated from the last one sent over the time that target stands for; a
  newer target ends the interpolation and goes out at once from where the device was last
  sent; a target superseded before its first write is never written (``superseded``);
- judges each device against what it was asked to do: a device whose measured joints stay
  further than a threshold from every target it was sent within its lag
  (:attr:`~beavr_sim.hardware.rig.MirrorConfig.device_lag_s`) for longer than a window holds
  (latched until :meth:`release` or the next :meth:`begin_episode`); a catch-up is judged the
  same way, so a reset never latches a hold;
- holds every device when no fresh command came within a timeout (a stalled twin, the pause
  between episodes): a hold that resumes, catching up, when commands come again;
- latches an emergency stop (:meth:`estop`) that holds every device until :meth:`release`;
- rides out a device that stops answering (a read or write raises
  :class:`~beavr_sim.hardware.device.DeviceError`): it is in ``OUTAGE`` and every other device
  holds; it is reconnected every :data:`RECONNECT_INTERVAL_S` for up to
  :attr:`~beavr_sim.hardware.rig.MirrorConfig.reconnect_s`; back in time and where it was held,
  it resumes through a guarded catch-up (``recovered``); otherwise it is ``FAILED`` (and the
  rest of the rig holds) until the operator re-arms it (:meth:`rearm`, also part of
  :meth:`release`);
- refuses to start when a device cannot be reached (:meth:`connect` names it and what to check).

Threads: the twin's thread (submit, health, in_sync), one writer per device, and the operator's
inputs (estop, release, rearm: keyboard, browser) share one lock (``_cond``); every counter and
every device state is written under it, and a writer works from a frozen :class:`_Orders`
snapshot taken under it. Device state is a :class:`LinkState` plus a :class:`HoldReason` and a
one-line detail for people (never parsed). Statistics are bounded (a ring of the last writes).

Called once per control period it does what lockstep mirroring did (each step at most one
period's motion, catch-up at one period's catch-up step, streams over a whole period).
``dry_run`` does everything but the final write (the devices are connected and read).
"""

from __future__ import annotations

import enum
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from beavr_sim.hardware.detour import Detour, DetourConfig, plan_detour
from beavr_sim.hardware.device import Device, DeviceError, MirrorError
from beavr_sim.hardware.rig import BODY, RigConfig, build_device, joint_names_of
from beavr_sim.robots.embodiment import Embodiment, JointIndex
from beavr_sim.twin.guard import CollisionGuard, GuardConfig, GuardVerdict
from beavr_sim.twin.rate_limit import JointRateLimit

log = logging.getLogger(__name__)

#: The shortest time (s) a submit's motion is spread over. Two commands can arrive a fraction
#: of a millisecond apart (scheduling jitter); with their true spacing the second could barely
#: move (at a spacing of 0 not at all: the target would freeze until the next heartbeat). One
#: millisecond of motion at the speed cap is a few mrad, and a streamed device is bounded
#: further by its writer (each target spread over at least one of its stream intervals, no
#: step faster than 90 % of the device's own cap).
MIN_INTERVAL_S = 1e-3
#: Time (s) between reconnection attempts of a device in outage.
RECONNECT_INTERVAL_S = 0.2
#: Writes whose timing each device keeps (the ring the latency percentiles come from).
WRITE_LOG_SIZE = 16384
#: Fault lines kept per episode (all are counted: :attr:`HardwareMirror.faults_total`).
MAX_FAULTS = 100
#: How long (s) :meth:`HardwareMirror.close` waits for a writer thread (one inside a reconnect
#: waits for its driver's connect timeout).
JOIN_TIMEOUT_S = 5.0


class LinkState(enum.Enum):
    """What a device is doing."""

    #: Sent the twin's (guarded) targets.
    FOLLOWING = "following"
    #: Sent targets on the way to the twin's, at the catch-up speed (after a hold, a release,
    #: a reset, a recovery).
    CATCHING_UP = "catching_up"
    #: Stays where it is (the reason says why); resumes by itself or on :meth:`release`.
    HOLDING = "holding"
    #: Stopped answering; being reconnected (every other device holds).
    OUTAGE = "outage"
    #: Not recovered: stays out (and the rest of the rig holds) until :meth:`rearm`.
    FAILED = "failed"


class HoldReason(enum.Enum):
    """Why a device is not following (``NONE`` while it follows or catches up)."""

    NONE = "none"
    #: The emergency stop is latched.
    ESTOP = "estop"
    #: No fresh command within ``command_timeout_s`` (resumes when commands come again).
    TIMEOUT = "timeout"
    #: The measured joints stayed away from what it was sent (latched until a release).
    DIVERGED = "diverged"
    #: Another device is in outage or failed.
    OTHER_DEVICE = "other_device"
    #: A read or write raised (``OUTAGE``).
    DEVICE_ERROR = "device_error"
    #: Did not answer again within ``reconnect_s`` (``FAILED``).
    NO_ANSWER = "no_answer"
    #: Answered again, but away from where it was held (``FAILED``).
    MOVED = "moved"


#: States in which a device is sent the twin's targets.
_MOVING = (LinkState.FOLLOWING, LinkState.CATCHING_UP)
#: States of a device that is out (the others hold for it).
_OUT = (LinkState.OUTAGE, LinkState.FAILED)


@dataclass(frozen=True)
class DeviceHealth:
    """One device's state, for the session (cheap, immutable)."""

    name: str
    state: LinkState
    reason: HoldReason
    #: One line for people ("" while following).
    detail: str


@dataclass(frozen=True)
class MirrorHealth:
    """The rig's state at one moment (:meth:`HardwareMirror.health`)."""

    #: Every device following or catching up (a command-timeout hold counts as live while
    #: commands come again: it resumes at its writer's next wake); no e-stop, nothing held,
    #: diverged, in outage or failed.
    live: bool
    devices: tuple[DeviceHealth, ...]
    #: One line per fault since :meth:`HardwareMirror.begin_episode` (e-stop, divergence,
    #: outage, failure; not command timeouts), oldest first.
    episode_faults: tuple[str, ...]

    @property
    def failed(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.devices if d.state in _OUT)


@dataclass(frozen=True)
class Fixtures:
    """Where an episode's fixtures (the twin's mocap bodies) stand after its reset."""

    mocap_pos: np.ndarray
    mocap_quat: np.ndarray

    @classmethod
    def of(cls, data) -> Fixtures:
        """The fixtures of an env's ``MjData`` (copied)."""
        return cls(np.array(data.mocap_pos, dtype=np.float64), np.array(data.mocap_quat))


@dataclass(frozen=True)
class _Dispatch:
    """One submit as the writers see it (never mutated after it is made)."""

    seq: int
    target: np.ndarray  # action order
    twin: np.ndarray  # the twin's joints
    catching_up: tuple[bool, ...]  # per link: its target short of the twin's action
    t_dispatch: float  # perf_counter
    t_submit: float  # monotonic
    interval: float  # the time this target stands for

    def __post_init__(self) -> None:
        self.target.flags.writeable = False  # shared with the writers: read-only
        self.twin.flags.writeable = False


@dataclass(frozen=True)
class _Orders:
    """What one writer is to do, taken under the lock."""

    dispatch: _Dispatch
    #: (reason, detail) every device holds for (e-stop, another device out), or None.
    halt: tuple[HoldReason, str] | None
    latched: str  # this device's divergence hold ("" none)
    rearm: bool  # the operator asked to re-arm this (failed) device
    stopping: bool


class WriteLog:
    """Bounded timing of a device's writes: the last :data:`WRITE_LOG_SIZE` (monotonic time,
    latency in ms) pairs for percentiles, and the count and first/last times of all of them
    for the rate. Memory does not grow with the writes: the ring is resident from
    construction (np.zeros' pages would become resident one by one as the ring fills)."""

    def __init__(self, size: int = WRITE_LOG_SIZE):
        self._times = np.full(size, np.nan)
        self._latency = np.full(size, np.nan)
        self.count = 0
        self.first = math.nan
        self.last = math.nan

    def add(self, t: float, latency_ms: float) -> None:
        i = self.count % self._times.size
        self._times[i], self._latency[i] = t, latency_ms
        if self.count == 0:
            self.first = t
        self.last = t
        self.count += 1

    def _ordered(self, a: np.ndarray) -> np.ndarray:
        n = self._times.size
        if self.count <= n:
            return a[: self.count].copy()
        i = self.count % n
        return np.concatenate([a[i:], a[:i]])

    @property
    def times(self) -> np.ndarray:
        """The kept writes' times, oldest first."""
        return self._ordered(self._times)

    @property
    def latency_ms(self) -> np.ndarray:
        return self._ordered(self._latency)

    def rate_hz(self) -> float | None:
        span = self.last - self.first
        return round((self.count - 1) / span, 2) if self.count > 1 and span > 0 else None

    def summary(self) -> dict:
        lat = self.latency_ms
        return {
            "p50": float(np.percentile(lat, 50)) if lat.size else None,
            "p99": float(np.percentile(lat, 99)) if lat.size else None,
            "n": self.count,
            "window": int(lat.size),
        }


@dataclass
class DeviceStats:
    """One device's counters (written under the mirror's lock)."""

    #: Connected at some time during the run (stays True after close).
    connected: bool = False
    #: Connected now.
    connected_now: bool = False
    commands_sent: int = 0
    #: Ticks in which the twin's guard refused this device's effector (nothing was sent).
    commands_refused: int = 0
    #: Times the device was put on hold (timeout, divergence, e-stop, another device out).
    holds: int = 0
    #: Of those, on a command timeout (the pause between episodes, a stalled twin).
    timeout_holds: int = 0
    #: The furthest the measured joints were from what the device was asked (rad).
    max_divergence_rad: float = 0.0
    max_divergence_joint: str = ""
    errors: int = 0
    last_error: str = ""
    #: Times the device stopped answering, came back (within reconnect_s, where it was held),
    #: and was re-armed by the operator after failing.
    outages: int = 0
    recovered: int = 0
    rearmed: int = 0
    #: Targets limited to the catch-up speed.
    catch_up_steps: int = 0
    #: Catch-up targets the mirror's guard refused (the device held those joints).
    catch_up_refused: int = 0
    #: Targets slowed to the speed cap over the time since the previous submit.
    rate_limited: int = 0
    #: Dispatched targets never written: a newer one came before the writer took them.
    superseded: int = 0
    #: Streamed interpolations cut short by a newer target (which went out at once).
    preempted: int = 0
    #: Dispatches not written because this device's target had not changed (another
    #: device's command) and it was written within the last control period.
    unchanged: int = 0

    def __post_init__(self) -> None:
        self.writes = WriteLog()

    @property
    def write_times(self) -> list[float]:
        """Monotonic times of the last writes (at most :data:`WRITE_LOG_SIZE`)."""
        return self.writes.times.tolist()

    @property
    def write_latency_ms(self) -> list[float]:
        return self.writes.latency_ms.tolist()

    def summary(self) -> dict:
        return {
            "connected": self.connected,
            "connected_now": self.connected_now,
            "commands_sent": self.commands_sent,
            "commands_refused": self.commands_refused,
            "holds": self.holds,
            "timeout_holds": self.timeout_holds,
            "max_divergence_rad": round(self.max_divergence_rad, 4),
            "max_divergence_joint": self.max_divergence_joint,
            "errors": self.errors,
            "last_error": self.last_error,
            "outages": self.outages,
            "recovered": self.recovered,
            "rearmed": self.rearmed,
            "catch_up_steps": self.catch_up_steps,
            "catch_up_refused": self.catch_up_refused,
            "rate_limited": self.rate_limited,
            "superseded": self.superseded,
            "preempted": self.preempted,
            "unchanged": self.unchanged,
            "write_latency_ms": self.writes.summary(),
            "write_rate_hz": self.writes.rate_hz(),
        }


def one_line(exc: BaseException) -> str:
    """An error as one line (a driver's message names the device and what to check)."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, DeviceError) else f"{type(exc).__name__}: {text}"


def _log_error(message: str, *args) -> None:
    """One line; the traceback only with DEBUG logging on."""
    log.error(message, *args, exc_info=log.isEnabledFor(logging.DEBUG))


class _Link:
    """One device, its joints in the action, and its writer thread.

    Fields below the lock line are the mirror's shared state (read and written under
    ``mirror._cond``); the rest belong to the writer thread."""

    def __init__(
        self, mirror: HardwareMirror, k: int, device: Device, index: np.ndarray, part: str
    ):
        self.mirror = mirror
        self.k = k  # its place in the mirror's links
        self.device = device
        self.index = index
        self.part = part
        config = mirror.rig.mirror
        hand = part == "hand"
        self.divergence_limit = config.hand_divergence_rad if hand else config.arm_divergence_rad
        self.sync_tolerance = (
            config.hand_sync_tolerance_rad if hand else config.arm_sync_tolerance_rad
        )
        # Writer-thread state.
        self._seq_sent = 0
        self._diverged_since: float | None = None
        self._device_held = False  # device.hold() sent since the last write
        #: The last target sent whole (every step of its stream), as the mirror asked for it:
        #: what an unchanged dispatch is compared with (not ``last``: a device returns what
        #: it actually sent, quantized to its units, which never equals the float target).
        self._sent_target: np.ndarray | None = None
        #: (monotonic time, target sent) within the device's lag: what it was asked to do.
        self._asked: deque[tuple[float, np.ndarray]] = deque(maxlen=256)
        self._t_read = -math.inf
        #: The submit time of the dispatch last written: an unchanged target is written again
        #: once per control period of submits (the twin's clock, not the writer's latency).
        self._t_written_submit = -math.inf
        self._thread: threading.Thread | None = None
        # ---- shared, under mirror._cond ----
        self.stats = DeviceStats()
        self.state = LinkState.FOLLOWING
        self.reason = HoldReason.NONE
        self.detail = ""
        #: The last target sent, as the device took it.
        self.last: np.ndarray | None = None
        #: Where the device stands while it does not follow the dispatched stream (held,
        #: reconnected): the next submit starts from here. None while it follows.
        self.anchor: np.ndarray | None = None
        #: The device's joints as last read by its writer thread (once per control period),
        #: and the dispatch it had taken then.
        self.measured: np.ndarray | None = None
        self.measured_seq = -1
        self.latched = ""  # a divergence hold, until a release or an episode's start
        self.rearm_requested = False

    @property
    def name(self) -> str:
        return self.device.name

    @property
    def retries(self) -> int:
        """Packets the driver asked for again (its bounded retries)."""
        return int(getattr(self.device, "retries", getattr(self.device, "comm_retries", 0)))

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"mirror-{self.name}", daemon=True)
        self._thread.start()

    def join(self, timeout: float) -> bool:
        """Wait for the writer; True when it has ended."""
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    # ------------------------------------------------------------ state (writer side)
    def _set(self, state: LinkState, reason: HoldReason = HoldReason.NONE, detail: str = ""):
        """Under the mirror's lock."""
        self.state, self.reason, self.detail = state, reason, detail

    def _hold(self, reason: HoldReason, why: str) -> None:
        m = self.mirror
        with m._cond:
            changed = self.state is not LinkState.HOLDING or self.reason is not reason
            if self.state is not LinkState.HOLDING:
                self.stats.holds += 1
                self.stats.timeout_holds += reason is HoldReason.TIMEOUT
            self._set(LinkState.HOLDING, reason, why)
            if self.last is not None:
                self.anchor = self.last
        if changed:
            (log.info if reason is HoldReason.TIMEOUT else log.warning)(
                "%s holds: %s", self.name, why
            )
        if not self._device_held:
            self._device_held = True
            if not m.dry_run:
                try:
                    self.device.hold()
                except Exception as exc:
                    self._outage(exc)

    def _sent(self, q: np.ndarray, now: float) -> None:
        with self.mirror._cond:
            self.last = q
            self.stats.commands_sent += not self.mirror.dry_run
        self._asked.append((now, q))

    def _write(self, q: np.ndarray, d: _Dispatch, state: LinkState) -> None:
        """Send ``q``; a device that wants a stream gets it interpolated from the last target
        over the dispatch's interval (within one stream step and one control period), at its
        rate: the first step leaves at once, a newer dispatch ends the rest and a hold breaks
        it off."""
        m = self.mirror
        last = self.last
        steps = [q]
        rate = self.device.stream_hz
        if rate and last is not None:
            # The command's interval in steps at the device's rate, more if a step would pass
            # the device's own speed cap (90 % of it per step).
            interval = min(max(d.interval, 1.0 / rate), m._period)
            n = max(1, round(interval * rate))
            if self.device.max_velocity:
                largest = float(np.max(np.abs(q - last), initial=0.0))
                n = max(n, math.ceil(largest / (0.9 * self.device.max_velocity / rate)))
            steps = [last + (q - last) * (k / n) for k in range(1, n + 1)]
        start = time.perf_counter()
        self._sent_target = None
        for k, step in enumerate(steps):
            if k:
                with m._cond:  # sleep to the next step; a new dispatch or a hold wakes us
                    m._cond.wait_for(
                        lambda: m._interrupts(self, d.seq),
                        timeout=max(0.0, start + k / rate - time.perf_counter()),
                    )
                    newer = m._dispatch.seq != d.seq
                    halted = m._interrupts(self, d.seq) and not newer
                    if newer and not halted:
                        self.stats.preempted += 1
                if halted or newer:
                    break  # a hold takes over; or the newer target goes out at once
            if not m.dry_run:
                sent = np.asarray(self.device.send_positions(step), dtype=np.float64)
            else:
                sent = np.asarray(step, dtype=np.float64)
            now = time.monotonic()
            self._sent(sent, now)
            if k == 0:
                self._t_written_submit = d.t_submit
                self._device_held = False
                with m._cond:
                    self.stats.writes.add(now, (time.perf_counter() - d.t_dispatch) * 1e3)
                    self.anchor = None
                    self._set(state)
        else:
            self._sent_target = q.copy()  # every step went out (no newer dispatch, no hold)

    # ------------------------------------------------------------ divergence
    def _asked_range(self, now: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Per joint, the lowest and highest target sent within the device's lag before
        ``now`` (and the one in effect at its start); None before any was sent."""
        lag = self.mirror.rig.mirror.device_lag_s
        asked = self._asked
        while len(asked) > 1 and asked[1][0] <= now - lag:
            asked.popleft()
        if not asked:
            return None
        qs = np.array([q for _, q in asked])
        return qs.min(axis=0), qs.max(axis=0)

    def _watch_divergence(self, measured: np.ndarray, now: float) -> None:
        """Hold the device when its measured joints stay further than the limit from what it
        was sent (within its lag) for longer than the window."""
        asked = self._asked_range(now)
        if asked is None:
            return
        lo, hi = asked
        gap = np.maximum(np.maximum(lo - measured, measured - hi), 0.0)
        divergence = float(np.max(gap))
        window = self.mirror.rig.mirror.divergence_window_s
        latch = ""
        if divergence <= self.divergence_limit:
            self._diverged_since = None
        elif self._diverged_since is None:
            self._diverged_since = now
        elif now - self._diverged_since > window:
            joint = self.device.joint_names[int(np.argmax(gap))]
            latch = (
                f"diverged: {joint} measured {divergence:.3f} rad from what it was sent for "
                f"{now - self._diverged_since:.2f} s (limit {self.divergence_limit} rad)"
            )
        m = self.mirror
        with m._cond:
            if divergence > self.stats.max_divergence_rad:
                self.stats.max_divergence_rad = divergence
                self.stats.max_divergence_joint = self.device.joint_names[int(np.argmax(gap))]
            if latch and not self.latched:
                self.latched = latch
                m._fault(f"{self.name} {latch}")
                m._cond.notify_all()

    def _read(self) -> np.ndarray:
        q = np.asarray(self.device.read_positions(), dtype=np.float64)
        self._t_read = time.monotonic()
        with self.mirror._cond:
            self.measured = q
            self.measured_seq = self._seq_sent
        return q

    # ------------------------------------------------------------ outage and re-arm
    def _outage(self, exc: BaseException) -> None:
        """The device stopped answering: every other device holds while it is reconnected
        (every RECONNECT_INTERVAL_S, for up to reconnect_s); back where it was held, it
        resumes (catching up); else it fails until re-armed."""
        m = self.mirror
        config = m.rig.mirror
        message = one_line(exc)
        with m._cond:
            self.stats.errors += 1
            self.stats.outages += 1
            self.stats.last_error = message
            # Where it was: between its last reading and its last target (a device finishing
            # its last move, or fingers stopped on what they hold, is where it was held).
            where = [q for q in (self.measured, self.last) if q is not None]
            self._set(LinkState.OUTAGE, HoldReason.DEVICE_ERROR, message)
            m._fault(f"{self.name} stopped answering: {message}")
            m._cond.notify_all()
        _log_error(
            "%s stopped answering: %s; every device holds; reconnecting for up to %g s",
            self.name,
            message,
            config.reconnect_s,
        )
        deadline = time.monotonic() + config.reconnect_s
        while True:
            if m._stopping.wait(RECONNECT_INTERVAL_S):
                return
            try:
                q = self._reconnect()
                break
            except Exception as retry_exc:  # any driver failure: retry
                message = one_line(retry_exc)
                log.debug("%s: reconnect failed: %s", self.name, message)
                if time.monotonic() >= deadline:
                    self._failed(
                        HoldReason.NO_ANSWER,
                        f"no answer within reconnect_s = {config.reconnect_s:g} s: {message}",
                    )
                    return
        moved = 0.0
        if where:
            lo, hi = np.minimum.reduce(where), np.maximum.reduce(where)
            moved = float(np.max(np.maximum(np.maximum(lo - q, q - hi), 0.0), initial=0.0))
        if moved > self.sync_tolerance:
            self._failed(
                HoldReason.MOVED,
                f"answered again {moved:.3f} rad from where it was held (tolerance "
                f"{self.sync_tolerance} rad): moved while it did not answer",
            )
            return
        with m._cond:
            self.stats.recovered += 1
            self._resume(q)
        log.warning("%s answers again where it was held: resuming (catching up)", self.name)

    def _reconnect(self) -> np.ndarray:
        q = np.asarray(self.device.reconnect(), dtype=np.float64)
        with self.mirror._cond:
            self.stats.connected = self.stats.connected_now = True
        return q

    def _resume(self, q: np.ndarray) -> None:
        """Under the lock: the device stands at ``q`` (just read) and follows from there."""
        self.last = self.anchor = self.measured = q
        self._sent_target = None
        self._asked.clear()
        self._asked.append((time.monotonic(), q))
        self._diverged_since = None
        self._device_held = False
        self._set(LinkState.CATCHING_UP)
        self.mirror._cond.notify_all()

    def _failed(self, reason: HoldReason, why: str) -> None:
        m = self.mirror
        with m._cond:
            self._set(LinkState.FAILED, reason, why)
            m._fault(f"{self.name} failed: {why}")
            m._cond.notify_all()
        _log_error(
            "%s failed: %s; every other device holds; check it, then re-arm it (r, or the "
            "browser's release button)",
            self.name,
            why,
        )

    def _rearm(self) -> None:
        """The operator re-armed this failed device: reconnect, re-read, follow from there."""
        m = self.mirror
        try:
            q = self._reconnect()
        except Exception as exc:  # any driver failure: it stays failed
            message = one_line(exc)
            with m._cond:
                self.rearm_requested = False
                self.stats.errors += 1
                self.stats.last_error = message
                self._set(LinkState.FAILED, self.reason, f"re-arm failed: {message}")
                m._cond.notify_all()
            _log_error("%s: re-arm failed: %s", self.name, message)
            return
        with m._cond:
            self.rearm_requested = False
            self.stats.rearmed += 1
            self._resume(q)
        log.warning("%s re-armed: following again (catching up)", self.name)

    # ------------------------------------------------------------ the writer
    def _run(self) -> None:
        m = self.mirror
        try:
            while True:
                with m._cond:
                    m._cond.wait_for(lambda: m._wakes(self), timeout=m._period)
                    orders = m._orders(self)
                    state = self.state
                if orders.stopping:
                    break
                self._serve(orders, state)
        except Exception as exc:  # a writer never dies silently
            _log_error("%s: mirror writer stopped: %s", self.name, one_line(exc))
            with m._cond:
                self._set(LinkState.FAILED, HoldReason.DEVICE_ERROR, one_line(exc))
                m._cond.notify_all()

    def _serve(self, orders: _Orders, state: LinkState) -> None:
        m = self.mirror
        d = orders.dispatch
        if state is LinkState.FAILED:
            if orders.rearm:
                self._rearm()
            return
        try:
            if orders.halt is not None:
                self._hold(*orders.halt)
                self._seq_sent = d.seq
                return
            if orders.latched:
                self._hold(HoldReason.DIVERGED, orders.latched)
                self._seq_sent = d.seq
                return
            if d.seq == self._seq_sent:  # nothing new: a dead twin, or the pause between
                timeout = m.rig.mirror.command_timeout_s  # episodes, holds (and resumes)
                if time.monotonic() - d.t_submit > timeout:
                    self._hold(HoldReason.TIMEOUT, f"no fresh command within {timeout:g} s")
                else:
                    self._read_when_idle()
                return
            with m._cond:
                self.stats.superseded += max(0, d.seq - self._seq_sent - 1)
            self._seq_sent = d.seq
            q = d.target[self.index]
            if (
                self._sent_target is not None
                and not self._device_held
                and state in _MOVING
                and d.t_submit - self._t_written_submit < 0.9 * m._period
                and np.array_equal(q, self._sent_target)
            ):
                # Unchanged (a command for another device): nothing to send; the same
                # target still goes out once per control period.
                with m._cond:
                    self.stats.unchanged += 1
                return
            moving = LinkState.CATCHING_UP if d.catching_up[self.k] else LinkState.FOLLOWING
            self._write(q, d, moving)
            # Read back once per control period, not after every write: commands come at
            # the headset's rate, the divergence watch needs no more, and a read is a bus
            # round trip the next write would wait behind.
            if time.monotonic() - self._t_read >= 0.9 * m._period:
                measured = self._read()
                if not m.dry_run:
                    self._watch_divergence(measured, self._t_read)
        except Exception as exc:  # any driver failure is an outage
            self._outage(exc)

    def _read_when_idle(self) -> None:
        """No new target for a control period: read the joints back (the writes read at most
        once a period, so the last one may not have been read) and watch the divergence."""
        if time.monotonic() - self._t_read < self.mirror._period:
            return
        measured = self._read()
        if not self.mirror.dry_run:
            self._watch_divergence(measured, self._t_read)


class HardwareMirror:
    """The devices of a rig following the twin's guarded commands (see the module docstring)."""

    def __init__(
        self,
        rig: RigConfig,
        embodiment: Embodiment,
        joints: JointIndex,
        model,
        control_hz: float,
        *,
        guard: GuardConfig | None = None,
        dry_run: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ):
        """``clock``: monotonic seconds, the time between submits is measured with (tests
        inject one)."""
        rig.check_embodiment(embodiment)
        self.rig = rig
        self.joints = joints
        self.dry_run = bool(dry_run)
        self._period = 1.0 / control_hz
        self._clock = clock
        guard_config = guard or GuardConfig()
        # The mirror's own guard checks the targets it makes itself (catching up).
        self.guard = CollisionGuard(model, embodiment, joints, guard_config, dt=self._period)
        self._qpos = np.zeros(model.nq)
        self._qpos[joints.qpos_adr] = joints.home
        self.links: list[_Link] = []
        for entry in rig.devices:
            device = build_device(entry, embodiment, joints)
            index = np.array([joints.names.index(n) for n in joint_names_of(entry, embodiment)])
            self.links.append(_Link(self, len(self.links), device, index, entry.part))
        effector_of = dict.fromkeys(embodiment.body_joints, BODY)  # the body: never refused
        for e in embodiment.effectors:
            for n in e.joints:
                effector_of[n] = e.name
        self._link_effector = [effector_of[joints.names[link.index[0]]] for link in self.links]
        vmax = self.guard.max_velocity.copy()
        for link in self.links:  # no faster than a device's own cap
            if link.device.max_velocity:
                vmax[link.index] = np.minimum(vmax[link.index], link.device.max_velocity)
        #: The speed caps, each joint on its own: a step beyond one period's reach is caught up.
        self._speed_limit = JointRateLimit.of(vmax)
        #: Per action index, the speed (rad/s) the rig follows (the guard's cap, no faster than
        #: a device's own): the twin steps no faster (``TwinInterface.follow_speed_caps``).
        self.speed_caps = vmax.copy()
        #: The rate limit: a device's joints move together (its step shortened along its
        #: direction); joints no device drives are not limited.
        driven = np.zeros(joints.size, dtype=bool)
        for link in self.links:
            driven[link.index] = True
        self._rate_limit = JointRateLimit.of(
            np.where(driven, vmax, math.inf), groups=[link.index for link in self.links]
        )
        hand = self.guard.hand_joints
        self._catch_up_limit = JointRateLimit.of(
            np.where(hand, rig.mirror.hand_catch_up_speed, rig.mirror.arm_catch_up_speed)
        )
        self._cond = threading.Condition()
        self._stopping = threading.Event()
        home = joints.home.astype(np.float64).copy()
        self._dispatch = _Dispatch(
            0, home, home.copy(), (False,) * len(self.links), 0.0, time.monotonic(), self._period
        )
        #: The time (``clock``) of the previous submit (none yet: the first stands for a whole
        #: period).
        self._t_previous = -math.inf
        #: What the last submit left of its action because of the rate limit (action - target;
        #: zero after a catch-up): distance the mirror still owes, not a jump of the twin.
        self._owed = np.zeros(joints.size)
        self._estop = ""  # why the e-stop is latched ("" = not)
        self._faults: list[str] = []  # since begin_episode
        self._faults_total = 0
        self._episodes = 0
        #: The last dispatch before the episode began: in sync needs reads after it.
        self._begin_seq = 0
        self._catch_up_refusals = 0  # (the twin's thread only)
        # A catch-up's way around a refused straight path (the twin's thread only): the legs
        # still to go, the goal it was planned for, the last action submitted.
        self._detour_config = DetourConfig()
        self._detour: list[np.ndarray] = []
        self._detour_goal: np.ndarray | None = None
        self._last_action: np.ndarray | None = None
        #: Every detour planned (found or not), oldest first.
        self.detours: list[Detour] = []
        self.started = False

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> np.ndarray:
        """Connect every device; returns the measured joints in action order (the twin starts
        there). Raises :class:`MirrorError` naming the device and what to check; devices
        already connected are released."""
        for link in self.links:
            try:
                link.device.connect()
            except (DeviceError, OSError, ValueError) as exc:
                self.close()
                raise MirrorError(f"cannot start mirroring: {link.name}: {exc}") from None
            with self._cond:
                link.stats.connected = link.stats.connected_now = True
        return self.measured()

    def measured(self) -> np.ndarray:
        """Measured joints of every device, in action order (home where no device); read
        now (before :meth:`start`: the writers read them afterwards)."""
        q = self.joints.home.astype(np.float64).copy()
        for link in self.links:
            measured = np.asarray(link.device.read_positions(), dtype=np.float64)
            with self._cond:
                link.measured = measured
            q[link.index] = measured
        return q

    def latest_measured(self) -> np.ndarray:
        """The devices' joints as their writer threads last read them (action order; the
        last dispatched target where a device has not been read yet)."""
        with self._cond:
            q = self._dispatch.target.copy()
            for link in self.links:
                if link.measured is not None:
                    q[link.index] = link.measured
        return q

    def start(self, q_start: np.ndarray) -> None:
        """Start following from ``q_start`` (the measured pose the twin was reset to)."""
        q = np.asarray(q_start, dtype=np.float64).copy()
        with self._cond:
            self._dispatch = _Dispatch(
                0, q, q.copy(), (False,) * len(self.links), 0.0, time.monotonic(), self._period
            )
            self._t_previous = -math.inf
            self._owed = np.zeros_like(q)
            for link in self.links:
                link.last = q[link.index].copy()
                link._asked.append((time.monotonic(), link.last))
        self.guard.reset()
        for link in self.links:
            link.start()
        self.started = True

    def begin_episode(self, q_start: np.ndarray, fixtures: Fixtures | None = None) -> None:
        """The twin was reset to ``q_start`` (action order) for a new episode.

        The mirror's guard is told this episode's ``fixtures`` (:meth:`Fixtures.of` the env's
        data after its reset) and forgets its motion history; a divergence hold is released
        and the episode's fault record cleared. The devices are then brought to ``q_start``
        by the guarded, speed-capped catch-up as the twin's submits (heartbeats while the
        operator is paused) come in; :meth:`in_sync` says when they are there. An e-stop
        stays latched and a failed device stays failed (:meth:`release`, :meth:`rearm`)."""
        q = np.asarray(q_start, dtype=np.float64)
        if q.shape != (self.joints.size,):
            raise ValueError(
                f"begin_episode: q_start has shape {q.shape}, not ({self.joints.size},)"
            )
        if fixtures is not None:
            self.guard.set_fixtures(fixtures.mocap_pos, fixtures.mocap_quat)
        self.guard.reset()
        self._detour, self._detour_goal, self._last_action = [], None, None
        with self._cond:
            self._episodes += 1
            self._begin_seq = self._dispatch.seq
            self._faults.clear()
            self._owed = np.zeros_like(self._owed)
            for link in self.links:
                link.latched = ""
                link._diverged_since = None
            self._cond.notify_all()

    def close(self) -> None:
        """Hold and release every device (idempotent)."""
        self._stopping.set()
        with self._cond:
            self._cond.notify_all()
        for link in self.links:
            ended = link.join(JOIN_TIMEOUT_S)
            if not ended:
                log.error("%s: its writer did not stop (a reconnect hangs): left as is", link.name)
                continue
            with self._cond:
                out = link.state in _OUT
            if link.stats.connected_now and not self.dry_run and not out:
                try:
                    link.device.hold()
                except Exception as exc:  # closing: note it, go on
                    with self._cond:
                        link.stats.errors += 1
                        link.stats.last_error = one_line(exc)
            link.device.disconnect()
            with self._cond:
                link.stats.connected_now = False

    # ------------------------------------------------------------------ per command
    def submit(
        self, action: np.ndarray, twin_positions: np.ndarray, refused: Sequence[str] = ()
    ) -> None:
        """The twin applied ``action`` (past its guard): a guarded command, or the period's
        heartbeat; its joints are ``twin_positions``; ``refused``: effectors whose command
        the guard refused."""
        if not self.started:
            raise RuntimeError("HardwareMirror.submit before start()")
        action = np.array(action, dtype=np.float64)  # a copy: the caller may reuse its array
        twin = np.array(twin_positions, dtype=np.float64)
        t = self._clock()
        dt = min(max(t - self._t_previous, 0.0), self._period)
        self._t_previous = t
        with self._cond:
            previous = self._dispatch.target.copy()
            owed = self._owed.copy()
            for link in self.links:  # a device not following starts from where it stands
                if link.anchor is not None:
                    previous[link.index] = link.anchor
                    owed[link.index] = 0.0
        step = action - previous
        rate_limited: list[int] = []
        caught, catch_up_refused = False, False
        interval = max(dt, MIN_INTERVAL_S)
        if self._speed_limit.exceeds(step - owed, self._period).any():
            # The twin is further than one period of motion away (not counting what the rate
            # limit still owes): catch up slowly, at the same speed whatever the submit rate,
            # guarded.
            caught = True
            target, verdict = self._catch_up_step(action, previous, interval)
            if not verdict.ok:
                for name in verdict.blocked:
                    sl = self.joints.slices[name]
                    target[sl] = previous[sl]
                catch_up_refused = True
            owed_next = np.zeros_like(action)
        else:
            # Within a period's motion, but no faster than the speed cap over the time since
            # the last submit: a device's step is shortened along its direction (its target
            # stays on the line to the guarded action); the rest is owed, not a jump.
            limited = self._rate_limit.clamp(previous, action, interval)
            target = limited.target
            rate_limited = [
                k for k, link in enumerate(self.links) if limited.limited[link.index].any()
            ]
            owed_next = action - target
        catching = tuple(
            bool(caught and (target[link.index] != action[link.index]).any()) for link in self.links
        )
        if catch_up_refused:
            self._catch_up_refusals += 1
            n = self._catch_up_refusals
            if n in (1, 10, 100) or n % 1000 == 0:
                log.warning(
                    "mirror catch-up refused: %s (the devices hold those joints; %d so far)",
                    verdict.reason(),
                    n,
                )
        with self._cond:
            for k, link in enumerate(self.links):
                if catching[k]:
                    link.stats.catch_up_steps += 1
                    link.stats.catch_up_refused += catch_up_refused
                if k in rate_limited:
                    link.stats.rate_limited += 1
                if self._link_effector[k] in refused:
                    link.stats.commands_refused += 1
            self._owed = owed_next
            self._dispatch = _Dispatch(
                self._dispatch.seq + 1,
                target,
                twin,
                catching,
                time.perf_counter(),
                time.monotonic(),
                dt,
            )
            self._cond.notify_all()

    def _catch_up_step(
        self, action: np.ndarray, previous: np.ndarray, interval: float
    ) -> tuple[np.ndarray, GuardVerdict]:
        """The next catch-up target toward ``action`` and the guard's verdict on it.

        Straight at the catch-up speed while the guard accepts that; when it refuses and the
        twin stands still (the same action twice: a sync), a detour is planned
        (:func:`~beavr_sim.hardware.detour.plan_detour`, once per goal) and its legs are
        followed instead, each step along its leg at the catch-up speed and checked again."""
        if self._detour_goal is not None and not np.array_equal(action, self._detour_goal):
            self._detour, self._detour_goal = [], None  # the twin moved on: that plan is stale
        while self._detour and np.array_equal(previous, self._detour[0]):
            self._detour.pop(0)
        cap = np.asarray(self._catch_up_limit.max_velocity) * interval
        if self._detour:
            return self._along(self._detour[0], previous, cap)
        target = self._catch_up_limit.clamp(previous, action, interval).target
        verdict = self.guard.check(target, self._qpos, previous)
        standing = self._last_action is not None and np.array_equal(action, self._last_action)
        self._last_action = action.copy()
        if verdict.ok or not standing or self._detour_goal is not None:
            return target, verdict
        self._detour_goal = action.copy()  # planned once per goal, found or not
        try:
            detour = plan_detour(self.guard, previous, action, self._qpos, self._detour_config)
        except Exception as exc:  # the per-tick path never raises: hold, say why
            log.warning("mirror catch-up: planning a detour failed: %s", one_line(exc))
            return target, verdict
        self.detours.append(detour)
        if not detour.found:
            log.warning(
                "mirror catch-up: the straight path is refused (%s) and %s: the devices hold",
                verdict.reason(),
                detour.reason,
            )
            return target, verdict
        log.info(
            "mirror catch-up: the straight path is refused (%s); going around (%s, %d legs)",
            verdict.reason(),
            detour.method,
            len(detour.waypoints),
        )
        self._detour = [w.copy() for w in detour.waypoints]
        return self._along(self._detour[0], previous, cap)

    def _along(
        self, waypoint: np.ndarray, previous: np.ndarray, cap: np.ndarray
    ) -> tuple[np.ndarray, GuardVerdict]:
        """One catch-up step on the straight leg ``previous`` -> ``waypoint`` (scaled as a
        whole, so the target stays on the leg the planner checked), guarded."""
        d = waypoint - previous
        ratio = float(np.max(np.abs(d) / cap, initial=0.0))
        target = waypoint.copy() if ratio <= 1.0 else previous + d / ratio
        return target, self.guard.check(target, self._qpos, previous)

    # ------------------------------------------------------------------ the writers' view
    def _halt_for(self, link: _Link) -> tuple[HoldReason, str] | None:
        """Under the lock: what every device but an out one holds for."""
        if self._estop:
            return HoldReason.ESTOP, f"e-stop: {self._estop}"
        for other in self.links:
            if other is not link and other.state in _OUT:
                return HoldReason.OTHER_DEVICE, f"{other.name} {other.state.value}"
        return None

    def _wakes(self, link: _Link) -> bool:
        """Under the lock: something for ``link``'s writer to do (a failed device waits for a
        re-arm; the others for a new dispatch, or a hold to take)."""
        if self._stopping.is_set() or link.rearm_requested:
            return True
        if link.state in _OUT:
            return False
        if self._dispatch.seq != link._seq_sent:
            return True
        halt = self._halt_for(link)
        want = halt[0] if halt is not None else (HoldReason.DIVERGED if link.latched else None)
        return want is not None and (link.state is not LinkState.HOLDING or link.reason is not want)

    def _interrupts(self, link: _Link, seq: int) -> bool:
        """Under the lock: a streamed interpolation of dispatch ``seq`` stops here."""
        return (
            self._dispatch.seq != seq
            or self._stopping.is_set()
            or bool(link.latched)
            or self._halt_for(link) is not None
        )

    def _orders(self, link: _Link) -> _Orders:
        return _Orders(
            self._dispatch,
            self._halt_for(link),
            link.latched,
            link.rearm_requested,
            self._stopping.is_set(),
        )

    def _fault(self, line: str) -> None:
        """Under the lock: a fault of this episode (the first MAX_FAULTS kept)."""
        if len(self._faults) < MAX_FAULTS:
            self._faults.append(line)
        self._faults_total += 1

    # ------------------------------------------------------------------ safety
    def estop(self, reason: str = "emergency stop") -> None:
        """Hold every device now; latched until :meth:`release`."""
        with self._cond:
            if not self._estop:
                self._fault(f"e-stop: {reason}")
            self._estop = reason or "emergency stop"
            self._cond.notify_all()
        log.error("EMERGENCY STOP (%s): every device holds until released", reason)

    def release(self) -> None:
        """Release the e-stop and any divergence hold, and re-arm failed devices (without
        waiting: see :meth:`rearm`); the devices catch up with the twin slowly."""
        with self._cond:
            self._estop = ""
            for link in self.links:
                link.latched = ""
                link._diverged_since = None
            self._cond.notify_all()
        if self.failed_devices:
            self.rearm(timeout_s=0.0)

    def rearm(self, timeout_s: float | None = None) -> list[str]:
        """Re-arm the failed devices (the operator checked them): each is reconnected and
        re-read by its writer and follows again from where it stands, through a guarded
        catch-up. Waits up to ``timeout_s`` (None: ``reconnect_s``) for the attempts; returns
        the devices still failed or in outage."""
        with self._cond:
            for link in self.links:
                if link.state is LinkState.FAILED:
                    link.rearm_requested = True
            self._cond.notify_all()
            wait = self.rig.mirror.reconnect_s if timeout_s is None else timeout_s
            if wait > 0 and self.started:
                self._cond.wait_for(
                    lambda: not any(link.rearm_requested for link in self.links), timeout=wait
                )
        return self.failed_devices

    @property
    def faults_total(self) -> int:
        """Faults (e-stops, divergences, outages, failures) over the whole session."""
        with self._cond:
            return self._faults_total

    @property
    def estopped(self) -> bool:
        return bool(self._estop)

    @property
    def failed_devices(self) -> list[str]:
        """Devices that failed (or are in outage) and are not recovered."""
        with self._cond:
            return [link.name for link in self.links if link.state in _OUT]

    # ------------------------------------------------------------------ state
    def health(self) -> MirrorHealth:
        """Every device's state now (cheap: one lock, no device access)."""
        with self._cond:
            fresh = time.monotonic() - self._dispatch.t_submit <= self.rig.mirror.command_timeout_s
            devices = tuple(
                DeviceHealth(link.name, link.state, link.reason, link.detail) for link in self.links
            )
            live = not self._estop and all(
                not link.latched
                and (
                    link.state in _MOVING
                    or (
                        link.state is LinkState.HOLDING
                        and link.reason is HoldReason.TIMEOUT
                        and fresh
                    )
                )
                for link in self.links
            )
            return MirrorHealth(live, devices, tuple(self._faults))

    def in_sync(self) -> bool:
        """Every device following (not catching up, not held) and its measured joints, read
        since the episode began (:meth:`begin_episode`), within its part's sync tolerance of
        the twin's."""
        with self._cond:
            if self._estop:
                return False
            twin = self._dispatch.twin
            for link in self.links:
                if (
                    link.state is not LinkState.FOLLOWING
                    or link.latched
                    or link.measured is None
                    or link.measured_seq <= self._begin_seq
                ):
                    return False
                gap = np.abs(link.measured - twin[link.index])
                if float(np.max(gap, initial=0.0)) > link.sync_tolerance:
                    return False
            return True

    # ------------------------------------------------------------------ report
    def summary(self) -> dict:
        out = {}
        with self._cond:
            for link in self.links:
                s = link.stats.summary()
                s["state"] = link.state.value
                s["reason"] = link.reason.value
                s["holding"] = link.detail if link.state is not LinkState.FOLLOWING else ""
                s["retries"] = link.retries
                out[link.name] = s
        return out
