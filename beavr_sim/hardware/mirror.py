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
  release, a reset) the device *catches up* at the slower catch-up speed, whatever the submit
  rate, each intermediate target checked by the mirror's own copy of the guard along its path;
- streams a device that wants a stream (:attr:`~beavr_sim.hardware.device.Device.stream_hz`)
  each target interpolated from the last one sent over the time that target stands for (one
  step, sent at once, at 90 Hz commands to a 100 Hz device); a newer target ends the
  interpolation and goes out at once from where the device was last sent; a target superseded
  before its first write is never written (``superseded``);
- holds a device whose measured joints stay further than a threshold from the twin's for longer
  than a window, and every device when no fresh command came within a timeout (a dead operator
  or twin), saying why; resumes (catching up) when commands come again;
- latches an emergency stop (:meth:`estop`) that holds every device until :meth:`release`;
- holds every other device when one fails (a vanished serial port, a controller error), and
  refuses to start when a device cannot be reached (:meth:`connect` names it and what to check).

Called once per control period it does what lockstep mirroring did (each step at most one
period's motion, catch-up at one period's catch-up step, streams over a whole period).
``dry_run`` does everything but the final write (the devices are connected and read).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.hardware.device import Device, DeviceError, MirrorError
from beavr_sim.hardware.rig import BODY, RigConfig, build_device, joint_names_of
from beavr_sim.robots.embodiment import Embodiment, JointIndex
from beavr_sim.twin.guard import CollisionGuard, GuardConfig

log = logging.getLogger(__name__)

#: The shortest time (s) a submit's motion is spread over. Two commands can arrive a fraction
#: of a millisecond apart (scheduling jitter); with their true spacing the second could barely
#: move (at a spacing of 0 not at all: the target would freeze until the next heartbeat). One
#: millisecond of motion at the speed cap is a few mrad, and a streamed device is bounded
#: further by its writer (each target spread over at least one of its stream intervals, no
#: step faster than 90 % of the device's own cap).
MIN_INTERVAL_S = 1e-3


@dataclass
class DeviceStats:
    connected: bool = False
    commands_sent: int = 0
    #: Ticks in which the twin's guard refused this device's effector (nothing was sent).
    commands_refused: int = 0
    #: Times the device was put on hold (timeout, divergence, e-stop, another device's failure).
    holds: int = 0
    max_divergence_rad: float = 0.0
    max_divergence_joint: str = ""
    errors: int = 0
    #: Why the device is holding now ("" while it follows the twin).
    holding: str = ""
    last_error: str = ""
    #: Targets limited to the catch-up speed.
    catch_up_steps: int = 0
    #: Targets slowed to the speed cap over the time since the previous submit (bunched
    #: commands: each within one period's motion, but too fast for their spacing).
    rate_limited: int = 0
    #: Dispatched targets never written: a newer one came before the writer took them.
    superseded: int = 0
    #: Streamed interpolations cut short by a newer target (which went out at once).
    preempted: int = 0
    #: Dispatches not written because this device's target had not changed (another
    #: device's command) and it was written within the last control period.
    unchanged: int = 0
    write_latency_ms: list[float] = field(default_factory=list)
    write_times: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        lat = np.asarray(self.write_latency_ms)
        return {
            "connected": self.connected,
            "commands_sent": self.commands_sent,
            "commands_refused": self.commands_refused,
            "holds": self.holds,
            "max_divergence_rad": round(self.max_divergence_rad, 4),
            "max_divergence_joint": self.max_divergence_joint,
            "errors": self.errors,
            "holding": self.holding,
            "last_error": self.last_error,
            "catch_up_steps": self.catch_up_steps,
            "rate_limited": self.rate_limited,
            "superseded": self.superseded,
            "preempted": self.preempted,
            "unchanged": self.unchanged,
            "write_latency_ms": {
                "p50": float(np.percentile(lat, 50)) if lat.size else None,
                "p99": float(np.percentile(lat, 99)) if lat.size else None,
                "n": int(lat.size),
            },
        }


class _Link:
    """One device, its joints in the action, and its writer thread."""

    def __init__(self, mirror: HardwareMirror, device: Device, index: np.ndarray, part: str):
        self.mirror = mirror
        self.device = device
        self.index = index
        config = mirror.rig.mirror
        self.divergence_limit = (
            config.hand_divergence_rad if part == "hand" else config.arm_divergence_rad
        )
        self.stats = DeviceStats()
        self._seq_sent = 0
        self._diverged_since: float | None = None
        self._held = False
        self._last: np.ndarray | None = None  # the last target sent, as the device took it
        #: The last target sent whole (every step of its stream), as the mirror asked for it:
        #: what an unchanged dispatch is compared with. Not ``_last``: a device returns what
        #: it actually sent, quantized to its units (encoder ticks, float32), which never
        #: equals the float target again.
        self._sent_target: np.ndarray | None = None
        #: The device's joints as last read by its writer thread (once per control period).
        self.measured: np.ndarray | None = None
        self._t_read = -math.inf
        self._t_write = -math.inf  # when a target last went out
        self._thread: threading.Thread | None = None

    @property
    def name(self) -> str:
        return self.device.name

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"mirror-{self.name}", daemon=True)
        self._thread.start()

    def join(self, timeout: float) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _hold(self, why: str) -> None:
        if self.stats.holding != why:
            if not self.stats.holding:
                self.stats.holds += 1
            log.warning("%s holds: %s", self.name, why)
            self.stats.holding = why
        if not self._held:
            self._held = True
            if not self.mirror.dry_run:
                try:
                    self.device.hold()
                except DeviceError as exc:
                    self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        self.stats.errors += 1
        self.stats.last_error = str(exc)
        self.mirror._device_failed(self, exc)

    def _write(
        self, q: np.ndarray, t_dispatch: float, now: float, seq: int, interval: float
    ) -> None:
        """Send ``q``; a device that wants a stream gets it interpolated from the last target
        over ``interval`` (the time since the submit before it, within one stream step and one
        control period), at its rate: the first step leaves at once, a newer dispatch (``seq``
        no longer the newest) ends the rest and a hold breaks it off."""
        m = self.mirror
        steps = [q]
        rate = self.device.stream_hz
        if rate and self._last is not None:
            # The command's interval in steps at the device's rate, more if a step would pass
            # the device's own speed cap (90 % of it per step).
            interval = min(max(interval, 1.0 / rate), m._period)
            n = max(1, round(interval * rate))
            if self.device.max_velocity:
                largest = float(np.max(np.abs(q - self._last), initial=0.0))
                n = max(n, math.ceil(largest / (0.9 * self.device.max_velocity / rate)))
            steps = [self._last + (q - self._last) * (k / n) for k in range(1, n + 1)]
        start = time.perf_counter()
        self._sent_target = None
        for k, step in enumerate(steps):
            if k:
                with m._cond:  # sleep to the next step; a new dispatch or a hold wakes us
                    m._cond.wait_for(
                        lambda: m._seq != seq or bool(m._halted) or m._stopping.is_set(),
                        timeout=max(0.0, start + k / rate - time.perf_counter()),
                    )
                    halted, newer = m._halted or m._stopping.is_set(), m._seq != seq
                if halted:
                    break  # a hold takes over from here
                if newer:
                    self.stats.preempted += 1
                    break  # the newer target goes out at once, from the last one sent
            if not m.dry_run:
                self._last = self.device.send_positions(step)
                self.stats.commands_sent += 1
            else:
                self._last = np.asarray(step, dtype=np.float64)
            if k == 0:
                self._t_write = time.monotonic()
                self.stats.write_latency_ms.append((time.perf_counter() - t_dispatch) * 1e3)
                self.stats.write_times.append(now)
                self._held = False
                self.stats.holding = ""
        else:
            self._sent_target = q.copy()  # every step went out (no newer dispatch, no hold)

    def _read_when_idle(self, m: HardwareMirror, twin: np.ndarray) -> None:
        """No new target for a control period: read the joints back (the writes read at most
        once a period, so the last one may not have been read) and watch the divergence."""
        if time.monotonic() - self._t_read < m._period:
            return
        try:
            self.measured = self.device.read_positions()
        except Exception as exc:  # a reader never dies silently: the device fails
            log.exception("%s: read failed", self.name)
            self._fail(exc if isinstance(exc, DeviceError) else DeviceError(repr(exc)))
            return
        finally:
            self._t_read = time.monotonic()
        if not m.dry_run:
            self._watch_divergence(m, self.measured, twin, self._t_read)

    def _watch_divergence(
        self, m: HardwareMirror, measured: np.ndarray, twin: np.ndarray, now: float
    ) -> None:
        """Hold the device when its measured joints stay further than the limit from the
        twin's for longer than the window."""
        gap = np.abs(measured - twin[self.index])
        divergence = float(np.max(gap))
        if divergence > self.stats.max_divergence_rad:
            self.stats.max_divergence_rad = divergence
            self.stats.max_divergence_joint = self.device.joint_names[int(np.argmax(gap))]
        if divergence <= self.divergence_limit:
            self._diverged_since = None
        elif self._diverged_since is None:
            self._diverged_since = now
        elif now - self._diverged_since > m.rig.mirror.divergence_window_s:
            self._hold(
                f"diverged: measured joints {divergence:.3f} rad from the twin's for "
                f"{now - self._diverged_since:.2f} s (limit {self.divergence_limit} rad)"
            )

    def _run(self) -> None:
        m = self.mirror
        while not m._stopping.is_set():
            with m._cond:
                m._cond.wait_for(
                    lambda: m._seq != self._seq_sent or m._stopping.is_set(), timeout=m._period
                )
                seq, target, t_dispatch = m._seq, m._dispatched, m._t_dispatch
                interval = m._interval
                twin = m._twin_positions
                halted = m._halted
                t_submit = m._t_submit
            if m._stopping.is_set():
                break
            if self.stats.holding.startswith("failed"):
                continue
            now = time.monotonic()
            if halted:
                self._hold(halted)
                self._seq_sent = seq
                continue
            if self.stats.holding.startswith("diverged"):
                self._seq_sent = seq
                continue  # latched until a release
            if now - t_submit > m.rig.mirror.command_timeout_s:
                self._hold(f"no fresh command within {m.rig.mirror.command_timeout_s:g} s")
                continue
            if seq == self._seq_sent:
                self._read_when_idle(m, twin)
                continue
            self.stats.superseded += max(0, seq - self._seq_sent - 1)
            self._seq_sent = seq
            q = target[self.index]
            if (
                self._sent_target is not None
                and not self._held
                and now - self._t_write < 0.9 * m._period
                and np.array_equal(q, self._sent_target)
            ):
                # Unchanged (a command for another device): nothing to send; the same
                # target still goes out once per control period.
                self.stats.unchanged += 1
                continue
            try:
                self._write(q, t_dispatch, now, seq, interval)
                # Read back once per control period, not after every write: commands come
                # at the headset's rate, the divergence watch needs no more, and a read is a
                # bus round trip the next write would wait behind.
                measured = None
                if time.monotonic() - self._t_read >= 0.9 * m._period:
                    measured = self.device.read_positions()
                    self._t_read = time.monotonic()
                    self.measured = measured
            except Exception as exc:  # a writer never dies silently: the device fails
                log.exception("%s: write failed", self.name)
                self._fail(exc if isinstance(exc, DeviceError) else DeviceError(repr(exc)))
                continue
            if m.dry_run or measured is None:
                continue
            self._watch_divergence(m, measured, twin, now)


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
            self.links.append(_Link(self, device, index, entry.part))
        effector_of = dict.fromkeys(embodiment.body_joints, BODY)  # the body: never refused
        for e in embodiment.effectors:
            for n in e.joints:
                effector_of[n] = e.name
        self._link_effector = [effector_of[joints.names[link.index[0]]] for link in self.links]
        vmax = self.guard.max_velocity.copy()
        for link in self.links:  # no faster than a device's own cap
            if link.device.max_velocity:
                vmax[link.index] = np.minimum(vmax[link.index], link.device.max_velocity)
        self._vmax = vmax
        self._step_cap = vmax * self._period
        hand = self.guard.hand_joints
        self._catch_up_cap = (
            np.where(hand, rig.mirror.hand_catch_up_speed, rig.mirror.arm_catch_up_speed)
            * self._period
        )
        self._cond = threading.Condition()
        self._stopping = threading.Event()
        self._seq = 0
        self._dispatched: np.ndarray | None = None
        self._t_dispatch = 0.0
        self._t_submit = time.monotonic()
        #: The time (``clock``) of the previous submit (none yet: the first stands for a whole
        #: period), and the time the dispatched target stands for (since the submit before
        #: it, within [0, period]).
        self._t_previous = -math.inf
        self._interval = self._period
        #: What the last submit left of its action because of the rate limit (action - target;
        #: zero after a catch-up): distance the mirror still owes, not a jump of the twin.
        self._owed = np.zeros(joints.size)
        self._twin_positions = joints.home.astype(np.float64).copy()
        self._halted = ""  # why every device holds ("" = none)
        self._estop = False
        self.started = False

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> np.ndarray:
        """Connect every device; returns the measured joints in action order (the twin starts
        there). Raises :class:`MirrorError` naming the device and what to check; devices
        already connected are released."""
        for link in self.links:
            try:
                link.device.connect()
                link.stats.connected = True
            except (DeviceError, OSError, ValueError) as exc:
                self.close()
                raise MirrorError(f"cannot start mirroring: {link.name}: {exc}") from None
        return self.measured()

    def measured(self) -> np.ndarray:
        """Measured joints of every device, in action order (home where no device)."""
        q = self.joints.home.astype(np.float64).copy()
        for link in self.links:
            link.measured = link.device.read_positions()
            q[link.index] = link.measured
        return q

    def latest_measured(self) -> np.ndarray:
        """The devices' joints as their writer threads last read them (action order; the
        last dispatched target where a device has not been read yet)."""
        q = (self._dispatched if self._dispatched is not None else self.joints.home).copy()
        for link in self.links:
            if link.measured is not None:
                q[link.index] = link.measured
        return q

    def start(self, q_start: np.ndarray) -> None:
        """Start following from ``q_start`` (the measured pose the twin was reset to)."""
        self._dispatched = np.asarray(q_start, dtype=np.float64).copy()
        self._twin_positions = self._dispatched.copy()
        self._t_submit = time.monotonic()
        self._t_previous = -math.inf
        self._owed = np.zeros_like(self._dispatched)
        self.guard.reset()
        for link in self.links:
            link._last = self._dispatched[link.index].copy()
            link._sent_target = None
            link.start()
        self.started = True

    def close(self) -> None:
        """Hold and release every device (idempotent)."""
        self._stopping.set()
        with self._cond:
            self._cond.notify_all()
        for link in self.links:
            link.join(2.0)
            if link.stats.connected and not self.dry_run:
                try:
                    link.device.hold()
                except DeviceError as exc:
                    link.stats.errors += 1
                    link.stats.last_error = str(exc)
            link.device.disconnect()
            link.stats.connected = False

    # ------------------------------------------------------------------ per command
    def submit(
        self, action: np.ndarray, twin_positions: np.ndarray, refused: Sequence[str] = ()
    ) -> None:
        """The twin applied ``action`` (past its guard): a guarded command, or the period's
        heartbeat; its joints are ``twin_positions``; ``refused``: effectors whose command
        the guard refused."""
        if self._dispatched is None:
            raise RuntimeError("HardwareMirror.submit before start()")
        action = np.array(action, dtype=np.float64)  # a copy: the caller may reuse its array
        t = self._clock()
        dt = min(max(t - self._t_previous, 0.0), self._period)
        self._t_previous = t
        previous = self._dispatched.copy()
        owed = self._owed.copy()
        for link in self.links:  # a holding device is where it was held, not where we sent
            if (self._halted or link.stats.holding) and link._last is not None:
                previous[link.index] = link._last
                owed[link.index] = 0.0
        step = action - previous
        target = action
        if (np.abs(step - owed) > self._step_cap * (1 + 1e-9)).any():
            # The twin is further than one period of motion away (not counting what the rate
            # limit still owes): catch up slowly, at the same speed whatever the submit rate,
            # guarded.
            cap = self._catch_up_cap * (max(dt, MIN_INTERVAL_S) / self._period)
            target = previous + np.clip(step, -cap, cap)
            verdict = self.guard.check(target, self._qpos, previous)
            if not verdict.ok:
                for name in verdict.blocked:
                    sl = self.joints.slices[name]
                    target[sl] = previous[sl]
                log.warning("mirror catch-up refused: %s", verdict.reason())
            for link in self.links:
                if (target[link.index] != action[link.index]).any():
                    link.stats.catch_up_steps += 1
            self._owed = np.zeros_like(action)
        else:
            # Within a period's motion, but no faster than the speed cap over the time since
            # the last submit: a device's step is shortened along its direction (its target
            # stays on the line to the guarded action); the rest is owed, not a jump.
            limit = self._vmax * max(dt, MIN_INTERVAL_S)
            for link in self.links:
                i = link.index
                ratio = float(np.max(np.abs(step[i]) / limit[i], initial=0.0))
                if ratio > 1 + 1e-9:
                    if target is action:
                        target = action.copy()
                    target[i] = previous[i] + step[i] / ratio
                    link.stats.rate_limited += 1
            self._owed = action - target
        for link, effector in zip(self.links, self._link_effector, strict=True):
            if effector in refused:
                link.stats.commands_refused += 1
        with self._cond:
            self._dispatched = target
            self._interval = dt
            self._twin_positions = np.asarray(twin_positions, dtype=np.float64).copy()
            self._t_dispatch = time.perf_counter()
            self._t_submit = time.monotonic()
            self._seq += 1
            self._cond.notify_all()

    # ------------------------------------------------------------------ safety
    def estop(self, reason: str = "emergency stop") -> None:
        """Hold every device now; latched until :meth:`release`."""
        with self._cond:
            self._estop = True
            self._halted = f"e-stop: {reason}"
            self._cond.notify_all()
        log.error("EMERGENCY STOP (%s): every device holds until released", reason)

    def release(self) -> None:
        """Release the e-stop and any divergence hold; devices catch up with the twin slowly."""
        with self._cond:
            if any(link.stats.holding.startswith("failed") for link in self.links):
                log.error("a device failed: restart the session to mirror again")
                return
            self._estop = False
            self._halted = ""
            for link in self.links:
                if link.stats.holding.startswith("diverged"):
                    link.stats.holding = ""
                    link._diverged_since = None
            self._cond.notify_all()

    @property
    def estopped(self) -> bool:
        return self._estop

    def _device_failed(self, link: _Link, exc: Exception) -> None:
        link.stats.holding = f"failed: {exc}"
        log.error("%s failed (%s): every other device holds", link.name, exc)
        with self._cond:
            self._halted = f"{link.name} failed"
            self._cond.notify_all()

    # ------------------------------------------------------------------ report
    def summary(self) -> dict:
        out = {}
        for link in self.links:
            s = link.stats.summary()
            times = np.asarray(link.stats.write_times)
            if times.size > 1:
                span = times[-1] - times[0]
                s["write_rate_hz"] = round((times.size - 1) / span, 2) if span > 0 else None
            out[link.name] = s
        return out
