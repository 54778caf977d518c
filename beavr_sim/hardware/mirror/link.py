"""One mirrored device and its writer thread (:class:`Link`).

The writer waits on the mirror's lock for something to do (a new dispatch, a hold to take, a
re-arm), takes a frozen :class:`~beavr_sim.hardware.mirror.dispatch.Orders` snapshot under it,
and serves it outside it: holds the device, sends the newest target (a device that wants a
stream gets it split by :func:`~beavr_sim.hardware.mirror.speed.stream_steps`, a newer target
or a hold breaking the stream off), reads the joints back once per control period for the
divergence watch, and rides out an outage (reconnect every :data:`RECONNECT_INTERVAL_S` for up
to ``reconnect_s``; resumed where it was held, else failed until re-armed).

Contract: the writer never dies silently (any exception fails the device, one line logged);
every field the mirror reads (state, counters, last target, measured joints) is written under
the mirror's lock; the fields above the lock line in :class:`Link` belong to the writer alone.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Protocol

import numpy as np

from beavr_sim.hardware.device import Device
from beavr_sim.hardware.mirror.dispatch import Dispatch, Orders
from beavr_sim.hardware.mirror.divergence import DivergenceWatch
from beavr_sim.hardware.mirror.errors import log, log_error, one_line
from beavr_sim.hardware.mirror.speed import stream_steps
from beavr_sim.hardware.mirror.state import MOVING, HoldReason, LinkState
from beavr_sim.hardware.mirror.stats import DeviceStats
from beavr_sim.hardware.rig import RigConfig

#: Time (s) between reconnection attempts of a device in outage.
RECONNECT_INTERVAL_S = 0.2


class Mirror(Protocol):
    """What a link's writer sees of the mirror that owns it (the shared lock and what is
    read under it)."""

    rig: RigConfig
    dry_run: bool
    _period: float
    _cond: threading.Condition
    _stopping: threading.Event
    _dispatch: Dispatch

    def _wakes(self, link: Link) -> bool: ...
    def _interrupts(self, link: Link, seq: int) -> bool: ...
    def _orders(self, link: Link) -> Orders: ...
    def _fault(self, line: str) -> None: ...


class Link:
    """One device, its joints in the action, and its writer thread.

    Fields below the lock line are the mirror's shared state (read and written under
    ``mirror._cond``); the rest belong to the writer thread."""

    def __init__(self, mirror: Mirror, k: int, device: Device, index: np.ndarray, part: str):
        self.mirror = mirror
        self.k = k  # its place in the mirror's links
        self.device = device
        self.index = index
        self.part = part
        config = mirror.rig.mirror
        hand = part == "hand"
        self.sync_tolerance = (
            config.hand_sync_tolerance_rad if hand else config.arm_sync_tolerance_rad
        )
        # Writer-thread state.
        self._seq_sent = 0
        #: What the device was asked within its lag, and how long it has been away from it.
        self.divergence = DivergenceWatch(
            config.device_lag_s,
            config.divergence_window_s,
            config.hand_divergence_rad if hand else config.arm_divergence_rad,
            device.joint_names,
        )
        self._device_held = False  # device.hold() sent since the last write
        #: The last target sent whole (every step of its stream), as the mirror asked for it:
        #: what an unchanged dispatch is compared with (not ``last``: a device returns what
        #: it actually sent, quantized to its units, which never equals the float target).
        self._sent_target: np.ndarray | None = None
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
    def divergence_limit(self) -> float:
        """How far (rad) its measured joints may stay from what it was sent."""
        return self.divergence.limit

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
        self.divergence.sent(now, q)

    def _write(self, q: np.ndarray, d: Dispatch, state: LinkState) -> None:
        """Send ``q``; a device that wants a stream gets it interpolated from the last target
        over the dispatch's interval (within one stream step and one control period), at its
        rate: the first step leaves at once, a newer dispatch ends the rest and a hold breaks
        it off."""
        m = self.mirror
        rate = self.device.stream_hz
        steps = stream_steps(self.last, q, d.interval, rate, m._period, self.device.max_velocity)
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
    def _watch_divergence(self, measured: np.ndarray, now: float) -> None:
        """Hold the device when its measured joints stay further than the limit from what it
        was sent (within its lag) for longer than the window."""
        judged = self.divergence.judge(measured, now)
        if judged is None:
            return
        m = self.mirror
        with m._cond:
            if judged.divergence > self.stats.max_divergence_rad:
                self.stats.max_divergence_rad = judged.divergence
                self.stats.max_divergence_joint = judged.joint
            if judged.latch and not self.latched:
                self.latched = judged.latch
                m._fault(f"{self.name} {judged.latch}")
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
        log_error(
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
        self.divergence.restart(time.monotonic(), q)
        self._device_held = False
        self._set(LinkState.CATCHING_UP)
        self.mirror._cond.notify_all()

    def _failed(self, reason: HoldReason, why: str) -> None:
        m = self.mirror
        with m._cond:
            self._set(LinkState.FAILED, reason, why)
            m._fault(f"{self.name} failed: {why}")
            m._cond.notify_all()
        log_error(
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
            log_error("%s: re-arm failed: %s", self.name, message)
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
            log_error("%s: mirror writer stopped: %s", self.name, one_line(exc))
            with m._cond:
                self._set(LinkState.FAILED, HoldReason.DEVICE_ERROR, one_line(exc))
                m._cond.notify_all()

    def _serve(self, orders: Orders, state: LinkState) -> None:
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
                and state in MOVING
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
