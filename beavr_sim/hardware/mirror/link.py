"""One mirrored device and its writer thread (:class:`Link`).

The writer waits, through its :class:`~beavr_sim.hardware.mirror.board.LinkPort`, for
something to do (a new dispatch, a hold to take, a re-arm), gets a frozen
:class:`~beavr_sim.hardware.mirror.dispatch.Orders` snapshot, and serves it: holds the device,
sends the newest target (a device that wants a stream gets it split by
:func:`~beavr_sim.hardware.mirror.speed.stream_steps`, a newer target or a hold breaking the
stream off), reads the joints back once per control period for the divergence watch, and
rides out an outage (reconnect every :data:`RECONNECT_INTERVAL_S` for up to ``reconnect_s``;
resumed where it was held, else failed until re-armed).

Contract: the writer never dies silently (any exception fails the device, one line logged);
it reports every change of what the mirror reads (state, counters, last target, measured
joints) through its port, which writes it under the mirror's one lock; the link touches no
lock and no field of another object. Its own fields belong to the writer thread, except
those the mirror's thread sets before the writer starts (:meth:`Link.restart_from`).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from beavr_sim.hardware.device import Device
from beavr_sim.hardware.mirror.board import DeviceShared, LinkPort
from beavr_sim.hardware.mirror.dispatch import Dispatch, Orders
from beavr_sim.hardware.mirror.divergence import DivergenceWatch
from beavr_sim.hardware.mirror.errors import log, log_error, one_line
from beavr_sim.hardware.mirror.speed import stream_steps
from beavr_sim.hardware.mirror.state import MOVING, HoldReason, LinkState

#: Time (s) between reconnection attempts of a device in outage.
RECONNECT_INTERVAL_S = 0.2


class Link:
    """One device, its joints in the action, and its writer thread.

    ``port``: the writer's way to the mirror's shared state; ``shared``: this device's record
    there (:class:`~beavr_sim.hardware.mirror.board.DeviceShared`), read by others under the
    mirror's lock and written only through the port. The other fields belong to the writer."""

    def __init__(
        self, port: LinkPort, shared: DeviceShared, device: Device, index: np.ndarray, part: str
    ):
        self.port = port
        self.k = port.k  # its place in the mirror's links
        self.shared = shared
        self.device = device
        self.index = index
        self.part = part
        config = port.config
        hand = part == "hand"
        self.sync_tolerance = (
            config.hand_sync_tolerance_rad if hand else config.arm_sync_tolerance_rad
        )
        # Writer-thread state.
        self._seq_sent = 0
        #: The newest dispatch the writer finished with (written whole, held, or judged
        #: unchanged): what a caller waiting for the writes to settle waits on.
        self.seq_served = 0
        #: What the device was asked within its lag, and how long it has been away from it.
        self.divergence = DivergenceWatch(
            config.device_lag_s,
            config.divergence_window_s,
            config.hand_divergence_rad if hand else config.arm_divergence_rad,
            device.joint_names,
        )
        #: Releases seen (each restarts the divergence timer).
        self._releases = 0
        self._device_held = False  # device.hold() sent since the last write
        #: The last target sent whole (every step of its stream), as the mirror asked for it:
        #: what an unchanged dispatch is compared with (not ``last``: a device returns what
        #: it actually sent, quantized to its units, which never equals the float target).
        self._sent_target: np.ndarray | None = None
        #: The last target sent, as the device took it (the writer's copy of ``shared.last``).
        self._last: np.ndarray | None = None
        self._t_read = -math.inf
        #: The submit time of the dispatch last written: an unchanged target is written again
        #: once per control period of submits (the twin's clock, not the writer's latency).
        self._t_written_submit = -math.inf
        self._thread: threading.Thread | None = None

    @property
    def name(self) -> str:
        return self.device.name

    # The shared record, read-only (for reports and tests; the mirror reads it under its lock).
    @property
    def stats(self):
        return self.shared.stats

    @property
    def state(self) -> LinkState:
        return self.shared.state

    @property
    def reason(self) -> HoldReason:
        return self.shared.reason

    @property
    def latched(self) -> str:
        return self.shared.latched

    @property
    def last(self) -> np.ndarray | None:
        return self.shared.last

    @property
    def measured(self) -> np.ndarray | None:
        return self.shared.measured

    @property
    def divergence_limit(self) -> float:
        """How far (rad) its measured joints may stay from what it was sent."""
        return self.divergence.limit

    @property
    def retries(self) -> int:
        """Packets the driver asked for again (its bounded retries)."""
        return int(getattr(self.device, "retries", getattr(self.device, "comm_retries", 0)))

    def restart_from(self, q: np.ndarray) -> None:
        """The device stands at ``q`` as mirroring starts (before :meth:`start`)."""
        self._last = q
        self.divergence.sent(time.monotonic(), q)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"mirror-{self.name}", daemon=True)
        self._thread.start()

    def join(self, timeout: float) -> bool:
        """Wait for the writer; True when it has ended."""
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    # ------------------------------------------------------------ writing
    def _hold(self, reason: HoldReason, why: str) -> None:
        changed = self.port.hold(reason, why)
        if changed:
            (log.info if reason is HoldReason.TIMEOUT else log.warning)(
                "%s holds: %s", self.name, why
            )
        if not self._device_held:
            self._device_held = True
            if not self.port.dry_run:
                try:
                    self.device.hold()
                except Exception as exc:
                    self._outage(exc)

    def _sent(self, q: np.ndarray, now: float) -> None:
        self._last = q
        self.port.sent(q)
        self.divergence.sent(now, q)

    def _write(self, q: np.ndarray, d: Dispatch, state: LinkState) -> None:
        """Send ``q``; a device that wants a stream gets it interpolated from the last target
        over the dispatch's interval (within one stream step and one control period), at its
        rate: the first step leaves at once, a newer dispatch ends the rest and a hold breaks
        it off."""
        port = self.port
        rate = self.device.stream_hz
        steps = stream_steps(self._last, q, d.interval, rate, port.period, self.device.max_velocity)
        start = time.perf_counter()
        self._sent_target = None
        for k, step in enumerate(steps):
            # Sleep to the next step; a new dispatch or a hold wakes the writer and ends it.
            if k and not port.wait_step(d.seq, max(0.0, start + k / rate - time.perf_counter())):
                break
            if not port.dry_run:
                sent = np.asarray(self.device.send_positions(step), dtype=np.float64)
            else:
                sent = np.asarray(step, dtype=np.float64)
            now = time.monotonic()
            self._sent(sent, now)
            if k == 0:
                self._t_written_submit = d.t_submit
                self._device_held = False
                port.wrote(now, (time.perf_counter() - d.t_dispatch) * 1e3, state)
        else:
            self._sent_target = q.copy()  # every step went out (no newer dispatch, no hold)

    # ------------------------------------------------------------ divergence
    def _watch_divergence(self, measured: np.ndarray, now: float) -> None:
        """Hold the device when its measured joints stay further than the limit from what it
        was sent (within its lag) for longer than the window."""
        judged = self.divergence.judge(measured, now)
        if judged is not None:
            self.port.judged(judged, self._releases)

    def _read(self) -> np.ndarray:
        q = np.asarray(self.device.read_positions(), dtype=np.float64)
        self._t_read = time.monotonic()
        self.port.read(q, self._seq_sent, self._t_read)
        return q

    # ------------------------------------------------------------ outage and re-arm
    def _outage(self, exc: BaseException) -> None:
        """The device stopped answering: every other device holds while it is reconnected
        (every RECONNECT_INTERVAL_S, for up to reconnect_s); back where it was held, it
        resumes (catching up); else it fails until re-armed."""
        config = self.port.config
        message = one_line(exc)
        # Where it was: between its last reading and its last target (a device finishing
        # its last move, or fingers stopped on what they hold, is where it was held).
        where = self.port.outage(message)
        log_error(
            "%s stopped answering: %s; every device holds; reconnecting for up to %g s",
            self.name,
            message,
            config.reconnect_s,
        )
        deadline = time.monotonic() + config.reconnect_s
        while True:
            if self.port.stopping(RECONNECT_INTERVAL_S):
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
        self._resume(q, rearmed=False)
        log.warning("%s answers again where it was held: resuming (catching up)", self.name)

    def _reconnect(self) -> np.ndarray:
        q = np.asarray(self.device.reconnect(), dtype=np.float64)
        self.port.connected()
        return q

    def _resume(self, q: np.ndarray, *, rearmed: bool) -> None:
        """The device stands at ``q`` (just read) and follows from there."""
        self._last = q
        self._sent_target = None
        self.divergence.restart(time.monotonic(), q)
        self._device_held = False
        self.port.resumed(q, rearmed=rearmed)

    def _failed(self, reason: HoldReason, why: str) -> None:
        self.port.failed(reason, why)
        log_error(
            "%s failed: %s; every other device holds; check it, then re-arm it (r, or the "
            "browser's release button)",
            self.name,
            why,
        )

    def _rearm(self) -> None:
        """The operator re-armed this failed device: reconnect, re-read, follow from there."""
        try:
            q = self._reconnect()
        except Exception as exc:  # any driver failure: it stays failed
            message = one_line(exc)
            self.port.rearm_failed(message)
            log_error("%s: re-arm failed: %s", self.name, message)
            return
        self._resume(q, rearmed=True)
        log.warning("%s re-armed: following again (catching up)", self.name)

    # ------------------------------------------------------------ the writer
    def _run(self) -> None:
        try:
            while True:
                orders = self.port.next_orders(self._seq_sent)
                if orders.stopping:
                    break
                self._serve(orders)
                self.seq_served = orders.dispatch.seq
        except Exception as exc:  # a writer never dies silently
            log_error("%s: mirror writer stopped: %s", self.name, one_line(exc))
            self.port.writer_died(one_line(exc))

    def _serve(self, orders: Orders) -> None:
        port = self.port
        d = orders.dispatch
        state = orders.state
        if orders.releases != self._releases:  # released, or a new episode: judged afresh
            self._releases = orders.releases
            self.divergence.since = None
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
                timeout = port.config.command_timeout_s  # episodes, holds (and resumes)
                if time.monotonic() - d.t_submit > timeout:
                    self._hold(HoldReason.TIMEOUT, f"no fresh command within {timeout:g} s")
                else:
                    self._read_when_idle()
                return
            port.superseded(d.seq - self._seq_sent - 1)
            self._seq_sent = d.seq
            q = d.target[self.index]
            if (
                self._sent_target is not None
                and not self._device_held
                and state in MOVING
                and d.t_submit - self._t_written_submit < 0.9 * port.period
                and np.array_equal(q, self._sent_target)
            ):
                # Unchanged (a command for another device): nothing to send; the same
                # target still goes out once per control period.
                port.unchanged()
                return
            moving = LinkState.CATCHING_UP if d.catching_up[self.k] else LinkState.FOLLOWING
            self._write(q, d, moving)
            # Read back once per control period, not after every write: commands come at
            # the headset's rate, the divergence watch needs no more, and a read is a bus
            # round trip the next write would wait behind.
            if time.monotonic() - self._t_read >= 0.9 * port.period:
                measured = self._read()
                if not port.dry_run:
                    self._watch_divergence(measured, self._t_read)
        except Exception as exc:  # any driver failure is an outage
            self._outage(exc)

    def _read_when_idle(self) -> None:
        """No new target for a control period: read the joints back (the writes read at most
        once a period, so the last one may not have been read) and watch the divergence."""
        if time.monotonic() - self._t_read < self.port.period:
            return
        measured = self._read()
        if not self.port.dry_run:
            self._watch_divergence(measured, self._t_read)
