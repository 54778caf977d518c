"""What a mirror's threads share, behind its one lock (:class:`MirrorBoard`), and the narrow
interface each device's writer gets to it (:class:`LinkPort`).

The board holds the lock (a condition), the newest :class:`~beavr_sim.hardware.mirror.dispatch.Dispatch`,
the e-stop, the episode's fault lines and one :class:`DeviceShared` record per device (its
state, counters, last target, measured joints). The mirror (the twin's thread, the operator's
inputs) works on it under :attr:`MirrorBoard.cond`; a writer thread only through its
:class:`LinkPort`, whose every method takes the lock itself: it waits for frozen
:class:`~beavr_sim.hardware.mirror.dispatch.Orders`, and reports what it did (held, sent,
wrote, read, lost the device, got it back, failed) as one call each.

Contract: every field of a :class:`DeviceShared` and every counter is written under the one
lock; a writer never holds the lock while it talks to its device, and never sees a record or
dispatch half written (it gets frozen snapshots).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.hardware.mirror.dispatch import Dispatch, Orders
from beavr_sim.hardware.mirror.divergence import Judgement
from beavr_sim.hardware.mirror.state import OUT, HoldReason, LinkState
from beavr_sim.hardware.mirror.stats import DeviceStats
from beavr_sim.hardware.rig import MirrorConfig

#: Fault lines kept per episode (all are counted: :attr:`MirrorBoard.faults_total`).
MAX_FAULTS = 100


@dataclass
class DeviceShared:
    """One device's state as every thread sees it (only under the board's lock)."""

    name: str
    stats: DeviceStats = field(default_factory=DeviceStats)
    state: LinkState = LinkState.FOLLOWING
    reason: HoldReason = HoldReason.NONE
    detail: str = ""
    #: The last target sent, as the device took it.
    last: np.ndarray | None = None
    #: Where the device stands while it does not follow the dispatched stream (held,
    #: reconnected): the next submit starts from here. None while it follows.
    anchor: np.ndarray | None = None
    #: The device's joints as last read, the dispatch its writer had taken then, and when
    #: (``time.monotonic()``).
    measured: np.ndarray | None = None
    measured_seq: int = -1
    measured_t: float = -math.inf
    #: A divergence hold ("" none), until a release or an episode's start.
    latched: str = ""
    rearm_requested: bool = False
    #: Releases and episode starts so far: a divergence timer started before the newest one
    #: does not latch (the writer restarts its timer when it sees the count move).
    releases: int = 0

    def set(self, state: LinkState, reason: HoldReason = HoldReason.NONE, detail: str = ""):
        self.state, self.reason, self.detail = state, reason, detail


class MirrorBoard:
    """The mirror's lock and what is read and written under it (see the module docstring)."""

    def __init__(self, names: Sequence[str], home: np.ndarray, period: float):
        self.cond = threading.Condition()
        self.stopping = threading.Event()
        self.period = period
        self.devices = [DeviceShared(name) for name in names]
        self.dispatch = Dispatch(
            0, home, home.copy(), (False,) * len(names), 0.0, time.monotonic(), period
        )
        self.estop = ""  # why the e-stop is latched ("" = not)
        self.faults: list[str] = []  # since the episode began
        self.faults_total = 0

    # ---------------------------------------------------------------- under the lock
    def fault(self, line: str) -> None:
        """Under the lock: a fault of this episode (the first MAX_FAULTS kept)."""
        if len(self.faults) < MAX_FAULTS:
            self.faults.append(line)
        self.faults_total += 1

    def halt_for(self, k: int) -> tuple[HoldReason, str] | None:
        """Under the lock: what every device but an out one holds for."""
        if self.estop:
            return HoldReason.ESTOP, f"e-stop: {self.estop}"
        for j, other in enumerate(self.devices):
            if j != k and other.state in OUT:
                return HoldReason.OTHER_DEVICE, f"{other.name} {other.state.value}"
        return None

    def wakes(self, k: int, seq_served: int) -> bool:
        """Under the lock: something for device ``k``'s writer to do (a failed device waits
        for a re-arm; the others for a new dispatch, or a hold to take)."""
        dev = self.devices[k]
        if self.stopping.is_set() or dev.rearm_requested:
            return True
        if dev.state in OUT:
            return False
        if self.dispatch.seq != seq_served:
            return True
        halt = self.halt_for(k)
        want = halt[0] if halt is not None else (HoldReason.DIVERGED if dev.latched else None)
        return want is not None and (dev.state is not LinkState.HOLDING or dev.reason is not want)

    def interrupts(self, k: int, seq: int) -> bool:
        """Under the lock: a streamed interpolation of dispatch ``seq`` stops here."""
        return (
            self.dispatch.seq != seq
            or self.stopping.is_set()
            or bool(self.devices[k].latched)
            or self.halt_for(k) is not None
        )

    def orders(self, k: int) -> Orders:
        """Under the lock: device ``k``'s writer's work, frozen."""
        dev = self.devices[k]
        return Orders(
            self.dispatch,
            self.halt_for(k),
            dev.latched,
            dev.rearm_requested,
            self.stopping.is_set(),
            dev.state,
            dev.releases,
        )

    def port(self, k: int, config: MirrorConfig, dry_run: bool) -> LinkPort:
        return LinkPort(self, k, config, dry_run)


class LinkPort:
    """All one writer thread may do with the board; each method takes the lock itself.

    ``k`` (the device's place), ``config``, ``period`` and ``dry_run``: the mirror's settings
    (immutable)."""

    def __init__(self, board: MirrorBoard, k: int, config: MirrorConfig, dry_run: bool):
        self._board = board
        self.k = k  # the device's place in the mirror's links
        self._dev = board.devices[k]
        self.config = config
        self.period = board.period
        self.dry_run = dry_run

    # ---------------------------------------------------------------- waiting
    def next_orders(self, seq_served: int) -> Orders:
        """Wait (at most a control period) for something to do; the orders then."""
        b = self._board
        with b.cond:
            b.cond.wait_for(lambda: b.wakes(self.k, seq_served), timeout=self.period)
            return b.orders(self.k)

    def wait_step(self, seq: int, timeout: float) -> bool:
        """Sleep up to ``timeout`` before the next step of dispatch ``seq``'s stream; False
        when a newer dispatch (counted as preempting it) or a hold broke it off."""
        b = self._board
        with b.cond:
            b.cond.wait_for(lambda: b.interrupts(self.k, seq), timeout=timeout)
            if b.dispatch.seq != seq:
                self._dev.stats.preempted += 1
                return False
            return not b.interrupts(self.k, seq)

    def stopping(self, timeout: float) -> bool:
        """Wait up to ``timeout`` for the mirror to close; whether it is closing."""
        return self._board.stopping.wait(timeout)

    # ---------------------------------------------------------------- reports
    def hold(self, reason: HoldReason, why: str) -> bool:
        """The device holds for ``reason``; whether that changed its state or reason."""
        dev = self._dev
        with self._board.cond:
            changed = dev.state is not LinkState.HOLDING or dev.reason is not reason
            if dev.state is not LinkState.HOLDING:
                dev.stats.holds += 1
                dev.stats.timeout_holds += reason is HoldReason.TIMEOUT
            dev.set(LinkState.HOLDING, reason, why)
            if dev.last is not None:
                dev.anchor = dev.last
        return changed

    def sent(self, q: np.ndarray) -> None:
        """``q`` went to the device (as it took it)."""
        with self._board.cond:
            self._dev.last = q
            self._dev.stats.commands_sent += not self.dry_run

    def wrote(self, now: float, latency_ms: float, state: LinkState) -> None:
        """The first step of a dispatch went out at ``now``: a write, timed; the device
        follows (``state``) from here."""
        dev = self._dev
        with self._board.cond:
            dev.stats.writes.add(now, latency_ms)
            dev.anchor = None
            dev.set(state)

    def superseded(self, n: int) -> None:
        """``n`` dispatches came and went before the writer took one."""
        if n > 0:
            with self._board.cond:
                self._dev.stats.superseded += n

    def unchanged(self) -> None:
        """A dispatch left this device's target as sent: nothing written."""
        with self._board.cond:
            self._dev.stats.unchanged += 1

    def read(self, q: np.ndarray, seq: int, now: float) -> None:
        """The device's joints were read (``q``) at ``now``, with dispatch ``seq`` taken."""
        with self._board.cond:
            self._dev.measured = q
            self._dev.measured_seq = seq
            self._dev.measured_t = now

    def judged(self, judged: Judgement, releases: int) -> None:
        """A reading judged (:class:`~beavr_sim.hardware.mirror.divergence.Judgement`) by a
        writer that had seen ``releases``: the largest divergence kept; a latch held, unless
        a release came since (its timer started before it)."""
        b, dev = self._board, self._dev
        with b.cond:
            if judged.divergence > dev.stats.max_divergence_rad:
                dev.stats.max_divergence_rad = judged.divergence
                dev.stats.max_divergence_joint = judged.joint
            if judged.latch and not dev.latched and releases == dev.releases:
                dev.latched = judged.latch
                b.fault(f"{dev.name} {judged.latch}")
                b.cond.notify_all()

    def outage(self, message: str) -> list[np.ndarray]:
        """The device stopped answering (``message``): in outage, every other device holds.
        Returns where it was: its last reading and its last target (those known)."""
        b, dev = self._board, self._dev
        with b.cond:
            dev.stats.errors += 1
            dev.stats.outages += 1
            dev.stats.last_error = message
            where = [q for q in (dev.measured, dev.last) if q is not None]
            dev.set(LinkState.OUTAGE, HoldReason.DEVICE_ERROR, message)
            b.fault(f"{dev.name} stopped answering: {message}")
            b.cond.notify_all()
        return where

    def connected(self) -> None:
        """The device answered a (re)connect."""
        with self._board.cond:
            self._dev.stats.connected = self._dev.stats.connected_now = True

    def resumed(self, q: np.ndarray, *, rearmed: bool) -> None:
        """The device is back (recovered from an outage, or re-armed), standing at ``q``:
        it follows from there, catching up."""
        b, dev = self._board, self._dev
        with b.cond:
            if rearmed:
                dev.rearm_requested = False
                dev.stats.rearmed += 1
            else:
                dev.stats.recovered += 1
            dev.last = dev.anchor = dev.measured = q
            dev.set(LinkState.CATCHING_UP)
            b.cond.notify_all()

    def failed(self, reason: HoldReason, why: str) -> None:
        """The device is out until re-armed (every other device holds)."""
        b, dev = self._board, self._dev
        with b.cond:
            dev.set(LinkState.FAILED, reason, why)
            b.fault(f"{dev.name} failed: {why}")
            b.cond.notify_all()

    def rearm_failed(self, message: str) -> None:
        """A re-arm's reconnect failed: it stays failed."""
        b, dev = self._board, self._dev
        with b.cond:
            dev.rearm_requested = False
            dev.stats.errors += 1
            dev.stats.last_error = message
            dev.set(LinkState.FAILED, dev.reason, f"re-arm failed: {message}")
            b.cond.notify_all()

    def writer_died(self, message: str) -> None:
        """The writer thread ends on an unexpected exception: the device fails."""
        b = self._board
        with b.cond:
            self._dev.set(LinkState.FAILED, HoldReason.DEVICE_ERROR, message)
            b.cond.notify_all()
