"""The in-process teleop loop: source -> validator -> operator -> twin, one tick at a time.

Used by tests, deterministic replay and the single-process CLI. On the virtual clock
(``real_time=False``) tick k happens at t = k * dt whatever the machine's speed, and the
source delivers the frames stamped up to that time: a replay is bit-for-bit repeatable. In
real time the loop is event-driven (``_event_tick``): each hand frame is observed and its
side commanded when it arrives, the command guarded and written to the twin's actuators (and
handed to the command hooks, e.g. the hardware mirror) at once; the physics steps once per
control period on ``time.monotonic()``, taking the frames that arrive meanwhile between its
substeps. Paced
(``paced=True``, virtual clock): the virtual clock's ticks, slept to the control rate - the
same deterministic replay, at the speed hardware moves (a mirrored trace replay).

Latency is measured per applied (non-hold, not refused) command from the moment its hand frame
entered the pipeline (received by the detector: ``t_receive`` in real time, the poll on the
virtual clock) to the moment the command, past the collision guard, is handed to the twin's
actuators.

The loop keeps running whatever its parts do. A paced tick that starts late (a stall) runs at
once and the wall deadlines it passed are skipped and counted (:class:`TickSchedule`), never
run back to back; the virtual clock still advances one period per tick, so a paced replay is
the same episode as an unpaced one. An exception in a tick listener is counted per listener
and logged, rate-limited (:class:`StopTeleop` alone ends the run on purpose); pure viewers run
on their own thread (:class:`ThreadedListener`). An exception from the operator holds every
effector for that tick (reason ``"error"``). Holds are counted per effector and reason.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from beavr_sim.headset.sources import HandSource
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.operator.obstacles import fixture_obstacles
from beavr_sim.operator.operator import Operator
from beavr_sim.teleop.interrupt import never
from beavr_sim.teleop.stages import (
    MIN_COMMAND_DT_S,
    OperatorStage,
    StopTeleop,
    TwinStage,
    count_hold,
    listener_name,
    operator_call,
    should_log,
)
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand, Tick, TickListener

log = logging.getLogger(__name__)

__all__ = [
    "MIN_COMMAND_DT_S",
    "StopTeleop",
    "TeleopLoop",
    "TeleopSummary",
    "ThreadedListener",
    "TickSchedule",
    "count_hold",
    "listener_name",
    "operator_call",
    "should_log",
]


class TickSchedule:
    """Wall-clock tick deadlines, one per ``dt``, that never catch up in a burst.

    ``next`` is the deadline of the next tick. A tick that starts after it (the one before
    overran, a stall, a slow set-up) runs at once and the grid moves on from it: the deadlines
    it passed are skipped and counted (``missed_ticks``), not run back to back; ``overruns``
    counts the ticks that started more than ``tolerance_s`` (a tenth of a period) late. The
    paced loop :meth:`wait` s for each deadline; the event-driven real-time loop and the twin
    process take commands until ``next`` and then step their physics, telling the schedule
    with :meth:`take`.
    """

    def __init__(self, dt: float, clock: Callable[[], float] = time.monotonic):
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"tick period must be positive and finite, got {dt}")
        self.dt = float(dt)
        self.tolerance_s = 0.1 * self.dt
        self.clock = clock
        self.next: float | None = None
        self.overruns = 0
        self.missed_ticks = 0

    def restart(self, first: float | None = None) -> None:
        """Start the grid over: the next tick is due at ``first`` (None: when it is asked)."""
        self.next = first

    def resume(self) -> None:
        """Forget a deadline that has passed (time spent outside the loop, e.g. setting up
        between two runs, is not an overrun); one still ahead is kept, so no two ticks run
        back to back across runs."""
        if self.next is not None and self.next < self.clock():
            self.next = None

    def take(self, now: float | None = None) -> float:
        """A tick starts at ``now``: count it if late and move the deadline on from the later
        of the deadline and ``now``. Returns the next deadline."""
        now = self.clock() if now is None else now
        if self.next is None:
            self.next = now
        late = now - self.next
        if late > self.tolerance_s:
            self.overruns += 1
            self.missed_ticks += int(late // self.dt)
        self.next = max(self.next, now) + self.dt
        return self.next

    def wait(self, sleep: Callable[[float], None] = time.sleep) -> float:
        """Sleep until the next deadline (not at all when late), then :meth:`take` the tick;
        returns its start on the grid."""
        now = self.clock()
        if self.next is not None and self.next > now:
            sleep(self.next - now)
            now = self.clock()
            if now - self.next <= self.tolerance_s:
                now = self.next  # on time: a sleep's usual overshoot does not move the grid
        self.take(now)
        return now


_EMPTY = object()


def concrete_seed(seed: int | None) -> int:
    """``seed``, or one drawn now where none is given. An episode's layout is always some
    seed's, so resetting to the episode's start again (after the rig's sync, a browser Reset)
    replays the same layout: the fixtures the mirror's guard was given at the sync's start
    are where the episode has them."""
    return int(np.random.SeedSequence().entropy % (1 << 31)) if seed is None else int(seed)


class LatencyLog:
    """Per-command latencies (ms) in bounded memory, read like the list they replace.

    ``append`` is O(1) and allocates nothing: the newest ``recent`` values sit in a ring
    (``log[-200:]``, ``log[k:]`` with ``k`` an absolute count, as a list of the values still
    held), and a uniform sample of all of them (reservoir sampling, at most ``sample``
    values; every value while fewer came) gives the percentiles. ``len()`` counts every value
    appended since the last :meth:`clear`. Both buffers are resident from construction, so a
    whole-day session holds the same megabyte as a minute's.
    """

    def __init__(self, recent: int = 1 << 16, sample: int = 1 << 16, seed: int = 0):
        if recent < 1 or sample < 1:
            raise ValueError(f"recent and sample must be >= 1, got {recent}, {sample}")
        # Written through now: np.zeros' pages become resident only when first written, so
        # the process's memory would creep up for as long as the buffers take to fill.
        self._ring = np.full(int(recent), np.nan)
        self._sample = np.full(int(sample), np.nan)
        self._rng = np.random.default_rng(seed)
        self._n = 0

    def append(self, value: float) -> None:
        n = self._n
        self._ring[n % self._ring.size] = value
        if n < self._sample.size:
            self._sample[n] = value
        else:
            j = int(self._rng.integers(0, n + 1))
            if j < self._sample.size:
                self._sample[j] = value
        self._n = n + 1

    def clear(self) -> None:
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, index):
        """A slice of the values appended (absolute positions; only those still in the ring
        come back) as a list; an integer index likewise."""
        n, size = self._n, self._ring.size
        first = max(0, n - size)  # the oldest value still held
        if isinstance(index, slice):
            start, stop, step = index.indices(n)
            if step != 1:
                raise ValueError("LatencyLog slices take no step")
            start = max(start, first)
            return [float(self._ring[i % size]) for i in range(start, max(start, stop))]
        i = index + n if index < 0 else index
        if not first <= i < n:
            raise IndexError(f"latency {index} is not held (held: {first}..{n - 1})")
        return float(self._ring[i % size])

    def __iter__(self):
        return iter(self[:])

    def percentiles(self) -> dict:
        """p50, p99 of the sample and the count of every value (the summary's shape)."""
        if not self._n:
            return {"p50": None, "p99": None, "n": 0}
        a = self._sample[: min(self._n, self._sample.size)]
        return {
            "p50": float(np.percentile(a, 50)),
            "p99": float(np.percentile(a, 99)),
            "n": self._n,
        }


class ThreadedListener[T]:
    """A tick listener run on its own thread, off the control tick: for pure viewers (the
    headset images), whose time must never add to the control period.

    On the control thread ``snapshot(tick)`` takes what the viewer needs - cheap copies, never
    the env's live ``MjData``, which the control thread steps meanwhile - or returns None to
    skip the tick (default: the tick itself). The worker thread gets the newest snapshot
    through a queue of one that drops the oldest: a slow viewer shows fewer frames, never old
    ones, and never slows the loop (``dropped`` counts what it skipped). ``target``'s
    exceptions are counted (``errors``, reported in the loop's ``listener_errors``) and logged,
    rate-limited. :meth:`close` stops the thread; ``target.close()``, if it has one, runs on
    that thread (where a render context lives).
    """

    def __init__(
        self,
        target: Callable[[T], None],
        *,
        snapshot: Callable[[Tick], T | None] | None = None,
        name: str | None = None,
    ):
        self.target = target
        self.snapshot = snapshot
        self.__name__ = name or listener_name(target)
        self.errors = 0
        self.dropped = 0
        self.handled = 0
        self._pending: object = _EMPTY
        self._closed = False
        self._wake = threading.Condition()
        self._thread = threading.Thread(
            target=self._work, name=f"listener-{self.__name__}", daemon=True
        )
        self._thread.start()

    def __call__(self, tick: Tick) -> None:
        item = tick if self.snapshot is None else self.snapshot(tick)
        if item is None:
            return
        with self._wake:
            if self._closed:
                return
            if self._pending is not _EMPTY:
                self.dropped += 1
            self._pending = item
            self._wake.notify()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _work(self) -> None:
        try:
            while True:
                with self._wake:
                    while self._pending is _EMPTY and not self._closed:
                        self._wake.wait()
                    if self._closed:
                        return
                    item, self._pending = self._pending, _EMPTY
                try:
                    self.target(item)  # type: ignore[arg-type]
                    self.handled += 1
                except Exception as exc:
                    self.errors += 1
                    if should_log(self.errors):
                        log.warning(
                            "tick listener %s failed (%d so far): %r",
                            self.__name__,
                            self.errors,
                            exc,
                            exc_info=self.errors == 1,
                        )
        finally:
            close = getattr(self.target, "close", None)
            if close is not None:
                try:
                    close()
                except Exception as exc:
                    log.warning("closing tick listener %s failed: %r", self.__name__, exc)

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop after the item in hand (a pending one is dropped); idempotent."""
        with self._wake:
            self._closed = True
            self._wake.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


@dataclass(frozen=True)
class RunRecord:
    """One run of a session (a play of a trace, a recorded episode): its line in the summary."""

    run: int
    #: The task's checker on the twin (the line's ``task_success``); the line's ``success``
    #: also needs the rig: no hardware fault and, when recording, the episode saved.
    success: bool
    duration_s: float
    #: What the hardware did wrong in this run ("" when nothing): the first fault's line.
    hardware_fault: str = ""
    #: Recording: whether the episode was written to the dataset (None: not recording).
    saved: bool | None = None
    #: Mirrored: wall seconds the rig took to reach the run's start pose (None: no rig).
    sync_s: float | None = None

    @property
    def true_success(self) -> bool:
        """Task success on the twin with the rig following all along (and, recording, saved)."""
        return self.success and not self.hardware_fault and self.saved is not False

    def to_dict(self) -> dict:
        out = asdict(self)
        out["success"] = self.true_success
        out["task_success"] = self.success
        out["duration_s"] = round(self.duration_s, 3)
        for key in ("saved", "sync_s"):
            if out[key] is None:
                del out[key]
        if self.sync_s is not None:
            out["sync_s"] = round(self.sync_s, 2)
        return out


#: Runs whose lines a session's summary keeps at each end (the first and the last this many);
#: the runs between are counted, not listed, so a day of ``--repeat`` holds what an hour does.
PER_RUN_KEPT = 50


class RunTally:
    """A session's runs in bounded form: every run counted (runs, successes, hardware faults,
    play and sync time), the lines (:meth:`RunRecord.to_dict`) of the first and the last
    ``kept`` runs kept, and how many lines between them were dropped.

    A success is a run that reached task success without a hardware fault and, when
    recording, whose episode was saved (``saved`` not False).
    """

    def __init__(self, kept: int = PER_RUN_KEPT):
        if kept < 1:
            raise ValueError(f"kept must be >= 1, got {kept}")
        self.kept = int(kept)
        self.runs = 0
        self.successes = 0
        self.hardware_faults = 0
        self.duration_s = 0.0
        self.longest_s = 0.0
        self.syncs = 0
        self.sync_s = 0.0
        self.slowest_sync_s = 0.0
        self._first: list[dict] = []
        self._last: deque[dict] = deque(maxlen=self.kept)
        #: The run just ended (None before the first).
        self.last: RunRecord | None = None

    def add(self, record: RunRecord) -> None:
        """Count ``record`` (the run just ended)."""
        self.runs += 1
        self.last = record
        self.successes += int(record.true_success)
        self.hardware_faults += int(bool(record.hardware_fault))
        self.duration_s += record.duration_s
        self.longest_s = max(self.longest_s, record.duration_s)
        if record.sync_s is not None:
            self.syncs += 1
            self.sync_s += record.sync_s
            self.slowest_sync_s = max(self.slowest_sync_s, record.sync_s)
        line = record.to_dict()
        if len(self._first) < self.kept:
            self._first.append(line)
        else:
            self._last.append(line)

    @property
    def dropped(self) -> int:
        """Runs counted whose lines are not kept (between the first and the last ``kept``)."""
        return self.runs - len(self._first) - len(self._last)

    def lines(self) -> list[dict]:
        """The kept runs' lines, oldest first."""
        return self._first + list(self._last)

    def report(self) -> dict:
        """The summary's run fields (plain data: JSON between processes), with the last
        run's line as ``last`` (None before the first)."""
        return {
            "runs": self.runs,
            "successes": self.successes,
            "hardware_faults": self.hardware_faults,
            "per_run": self.lines(),
            "per_run_kept": self.kept,
            "per_run_dropped": self.dropped,
            "run_totals": self.totals(),
            "last": self.last.to_dict() if self.last is not None else None,
        }

    def totals(self) -> dict:
        """Aggregates over every run (the summary's ``run_totals``)."""
        out: dict = {
            "duration_s": round(self.duration_s, 3),
            "mean_duration_s": round(self.duration_s / self.runs, 3) if self.runs else None,
            "longest_s": round(self.longest_s, 3),
        }
        if self.syncs:
            out["mean_sync_s"] = round(self.sync_s / self.syncs, 2)
            out["slowest_sync_s"] = round(self.slowest_sync_s, 2)
        return out


@dataclass
class TeleopSummary:
    task: str
    embodiment: str
    success: bool
    frames_received: int
    frames_rejected: int
    commands_applied: int
    duration_s: float
    latency_ms: dict
    rejected_by_reason: dict = field(default_factory=dict)
    #: Ticks each effector held, by reason: effector -> reason -> ticks (the operator's reasons,
    #: e.g. "paused", "tracking_lost", "error"; "guard": the collision guard refused the
    #: command; "step_limit": the twin clamped its step, where the twin counts that).
    holds: dict = field(default_factory=dict)
    operator: dict = field(default_factory=dict)
    ticks: int = 0
    loop_rate_hz: float | None = None
    processes: dict = field(default_factory=dict)
    #: Commands the collision guard refused, per effector.
    guard_blocks: dict = field(default_factory=dict)
    #: Per mirrored device (teleop --mirror-hardware): connected, commands sent and refused,
    #: holds, largest divergence from the twin, errors.
    hardware: dict = field(default_factory=dict)
    #: Exceptions raised by tick listeners, per listener (the loop went on).
    listener_errors: dict = field(default_factory=dict)
    #: Paced / real-time ticks that started late, and the control periods skipped after them
    #: (in --multiprocess: the operator's and the twin's loops together).
    overruns: int = 0
    missed_ticks: int = 0
    #: Valid frames replaced by a newer one of the same hand before any command used them
    #: (counted in ``frames_received`` too).
    frames_superseded: int = 0
    #: The session's runs (each play of a ``--repeat`` trace, each recorded episode), filled by
    #: the session runner; the fields above describe the last run (its counters: the session).
    runs: int = 0
    #: Runs that reached task success (recorded: and were saved as true episodes).
    successes: int = 0
    #: Runs ended or spoilt by the hardware (a device held, failed, diverged or never synced).
    hardware_faults: int = 0
    #: One line per run, oldest first (:class:`RunRecord` as a dict): the first and the last
    #: ``per_run_kept`` runs; ``per_run_dropped`` runs between them are counted, not listed.
    per_run: list = field(default_factory=list)
    per_run_kept: int = PER_RUN_KEPT
    per_run_dropped: int = 0
    #: Aggregates over every run (:meth:`RunTally.totals`: play time, mean and longest run,
    #: mean and slowest sync).
    run_totals: dict = field(default_factory=dict)
    #: Mirrored devices that failed and were not recovered (the CLI exits with code 4).
    failed_devices: list = field(default_factory=list)
    #: Why the session ended before all its runs were played ("" when it did not).
    stopped_early: str = ""
    #: The task's checker on the twin in the last run (None: no run counted). ``success`` is
    #: False where that run had a hardware fault: the twin finished, the rig did not follow.
    task_success: bool | None = None

    def count_runs(self, tally: RunTally) -> None:
        """Describe the session's runs (the session runner's :class:`RunTally`)."""
        self.take_runs(tally.report())

    def take_runs(self, report: dict) -> None:
        """Describe the session's runs from :meth:`RunTally.report` (which crosses from the
        ``--multiprocess`` twin as JSON)."""
        self.runs, self.successes = report["runs"], report["successes"]
        last = report["last"]
        if last is not None:
            self.task_success = bool(last["task_success"])
            if last["hardware_fault"]:
                self.success = False
        self.hardware_faults = report["hardware_faults"]
        self.per_run = list(report["per_run"])
        self.per_run_kept, self.per_run_dropped = report["per_run_kept"], report["per_run_dropped"]
        self.run_totals = dict(report["run_totals"])

    def to_dict(self) -> dict:
        return asdict(self)


def _percentiles(values_ms: Sequence[float]) -> dict:
    if not values_ms:
        return {"p50": None, "p99": None, "n": 0}
    a = np.asarray(values_ms)
    return {
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "n": len(a),
    }


class TeleopLoop:
    def __init__(
        self,
        twin: TwinInterface,
        operator: Operator,
        source: HandSource,
        *,
        validator: StreamValidator | None = None,
        real_time: bool = False,
        paced: bool = False,
        listeners: Sequence[TickListener] = (),
    ):
        self.twin = twin
        self.operator = operator
        self.source = source
        self.validator = validator or StreamValidator()
        self.real_time = bool(real_time)
        #: Sleep to the control rate on the virtual clock (real time implies it).
        self.paced = bool(paced) or self.real_time
        self.listeners = list(listeners)
        self.dt = 1.0 / twin.env.control_hz
        self.frames_received = 0
        #: Exceptions raised by (synchronous) tick listeners and twin hooks, per name.
        self.listener_errors: dict[str, int] = {}
        #: The two stages of the per-frame path (shared with the ``--multiprocess`` runner).
        self.operator_stage = OperatorStage(
            operator,
            twin.env.control_hz,
            hold_positions=lambda name: self.twin.action[self.twin.slices[name]].copy(),
            source_finished=lambda: self.source.finished,
        )
        self.twin_stage = TwinStage(twin, hook_errors=self.listener_errors, latencies=LatencyLog())
        #: Per applied command (ms; see the module docstring), bounded (:class:`LatencyLog`).
        self.latencies_ms: LatencyLog = self.twin_stage.latencies_ms
        #: Ticks each effector held, by reason (see :attr:`TeleopSummary.holds`).
        self.holds: dict[str, dict[str, int]] = self.operator_stage.holds
        #: Exceptions raised by the operator (each one a tick of holds), per call.
        self.operator_errors: dict[str, int] = self.operator_stage.errors
        #: Wall deadlines of paced ticks (started when the loop first runs, not at reset).
        self.schedule = TickSchedule(self.dt)
        self.ticks = 0
        #: Seed of the current episode (reset with the same seed re-runs the same layout).
        self.seed: int | None = None
        #: How many times the loop was reset (a reset during :meth:`run` starts the wait for
        #: the end of the source over).
        self.resets = 0
        #: Valid frames replaced by a newer one of the same hand before a command used them
        #: (in all, and per hand).
        self.frames_superseded = 0
        self.superseded_by_side: dict[str, int] = {}
        #: Real time: commands made for a hand frame on its arrival (one per side and frame,
        #: or per the newest of frames that arrived together).
        self.frame_commands = 0
        #: Called with each :class:`~beavr_sim.twin.twin.CommandOutcome` and the commands
        #: (effector -> JointCommand) the moment the twin applied them (real time: a command
        #: per hand frame), e.g. the hardware mirror: the twin stage's ``after_command`` hooks.
        self.command_hooks: list[Callable] = self.twin_stage.after_command
        self._sides = list(self.operator_stage.sides)
        # Real time: what arrived since the last physics step (the next tick's frames, the
        # newest command per effector, the sides commanded by a frame).
        self._pending_frames: list = []
        self._pending_commands: dict[str, JointCommand] = {}
        self._pending_sides: set[str] = set()
        #: Asked after every tick of :meth:`run`: true ends the run (Ctrl-C / SIGTERM,
        #: :mod:`beavr_sim.teleop.interrupt`); the session then ends in order.
        self.interrupted: Callable[[], bool] = never

    # ------------------------------------------------------------------ control
    def reset(self, seed: int | None = None, robot_qpos: np.ndarray | None = None) -> None:
        """Reset the twin (new episode; the robot at ``robot_qpos`` or home) and re-home the
        operator from the measured joints. No ``seed``: one is drawn (:func:`concrete_seed`)
        and kept in :attr:`seed`, so ``reset(loop.seed)`` replays this layout."""
        seed = concrete_seed(seed)
        self.seed = seed
        self.resets += 1
        q = self.twin_stage.reset(seed, robot_qpos)
        self.operator.reset(q, self.twin.slices)
        env = self.twin.env
        self.operator.set_obstacles(fixture_obstacles(env.model, env.data))
        self.ticks = 0

    def replace_source(self, source: HandSource) -> None:
        """A new stream (e.g. a trace played again from its start): its timestamps start over,
        so the validator's ordering check starts over too."""
        self.source = source
        self.validator.reset()

    def now(self) -> float:
        return time.monotonic() if self.real_time else self.ticks * self.dt

    # ------------------------------------------------------------------ one tick
    def tick(self) -> Tick:
        """One tick; paced, first waits for its wall deadline (at once when late: see
        :class:`TickSchedule`). In real time the tick is event-driven
        (:meth:`_event_tick`)."""
        if self.real_time:
            return self._event_tick()
        if self.paced:
            self.schedule.wait()
        now = self.now()
        poll_wall = time.perf_counter()
        used = []
        for frame in self.source.poll(now):
            self.frames_received += 1
            if self.source.validates or self.validator.check(frame) is None:
                used.append(frame)
        stage = self.operator_stage
        ok = stage.observe(used)
        commands = stage.command(now, ok)
        state = self.twin_stage.apply(commands, entered_perf=poll_wall, latency=bool(used))
        self._resync_blocked(state.guard_blocked_effectors)
        self.ticks += 1
        tick = Tick(t=now, frames=tuple(used), commands=commands, state=state)
        self._notify(tick)
        return tick

    def _event_tick(self) -> Tick:
        """Real time: until the physics' next deadline, each hand frame is processed when it
        arrives (validated, observed, its side's effectors commanded, the command guarded and
        written to the twin's actuators, the command hooks called); then the physics steps
        one control period, taking the frames that arrive meanwhile between its substeps
        (they count for the next tick). A side without a frame in the period is commanded at
        the step (its holds: waiting, tracking lost, paused)."""
        deadline = self.schedule.next
        while deadline is not None:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self._take_frames(self.source.wait(remaining))
        self._take_frames(self.source.poll(self.now()))
        self.schedule.take(time.monotonic())
        now = self.now()
        for side in self._sides:
            if side not in self._pending_sides:
                self._command_side(side, now, True, self._pending_commands)
        used, commands = self._pending_frames, self._pending_commands
        self._pending_frames, self._pending_commands, self._pending_sides = [], {}, set()
        env = self.twin.env
        env.between_substeps = self._frames_between_substeps
        try:
            state = self.twin_stage.step()
        finally:
            env.between_substeps = None
        self.ticks += 1
        tick = Tick(t=now, frames=tuple(used), commands=commands, state=state)
        self._notify(tick)
        return tick

    def _frames_between_substeps(self) -> None:
        frames = self.source.poll(self.now())
        if frames:
            self._take_frames(frames)

    def _take_frames(self, frames) -> None:
        by_side: dict[str, list] = {}
        used = []
        for frame in frames:
            self.frames_received += 1
            if self.source.validates or self.validator.check(frame) is None:
                used.append(frame)
                by_side.setdefault(getattr(frame, "side", None), []).append(frame)
        ok = self.operator_stage.observe(used)
        self._pending_frames.extend(used)
        now = self.now()
        for side, frames_of_side in by_side.items():
            if side not in self.operator_stage.last_command:
                continue  # a hand this embodiment does not use (the operator counted it)
            self.frames_superseded += len(frames_of_side) - 1
            self.superseded_by_side[side] = (
                self.superseded_by_side.get(side, 0) + len(frames_of_side) - 1
            )
            self.frame_commands += 1
            self._pending_sides.add(side)
            self._command_side(side, now, ok, self._pending_commands)

    def _command_side(self, side: str, now: float, ok: bool, commands: dict) -> None:
        """Command ``side``'s effectors now and apply the commands to the twin at once (the
        twin stage's ``after_command`` hooks: the command hooks)."""
        out = self.operator_stage.command_side(side, now, ok)
        outcome = self.twin_stage.command(out)
        self._resync_blocked(outcome.blocked)
        commands.update(out)

    def _resync_blocked(self, blocked) -> None:
        """The guard refused these effectors' commands: count it, and continue each from
        where the twin holds it (its target in the action)."""
        for name in blocked:
            self.operator_stage.guard_refused(name, self.twin.action[self.twin.slices[name]])

    def _notify(self, tick: Tick) -> None:
        for listener in self.listeners:
            try:
                listener(tick)
            except StopTeleop:
                raise
            except Exception as exc:
                self.listener_error(listener_name(listener), exc)

    def _hold_all(self, reason: str) -> dict[str, JointCommand]:
        """A hold of every effector at the twin's last target (nothing moves, nothing jumps)."""
        return self.operator_stage.hold(reason, self.operator.effectors)

    def listener_error(self, name: str, exc: BaseException) -> None:
        """Count (and log, rate-limited) an exception a tick listener raised."""
        n = self.listener_errors[name] = self.listener_errors.get(name, 0) + 1
        if should_log(n):
            log.warning(
                "tick listener %s failed (%d so far): %r; teleoperation goes on",
                name,
                n,
                exc,
                exc_info=n == 1,
            )

    # ------------------------------------------------------------------ episode
    def run(
        self,
        max_seconds: float | None = None,
        stop_on_success: bool = True,
        tail_seconds: float = 2.0,
        progress: Callable[[Tick], None] | None = None,
        stop_when: Callable[[], bool] | None = None,
    ) -> TeleopSummary:
        """Tick until success / failure / the env's time limit / ``max_seconds`` / the end of
        a finite source plus ``tail_seconds`` (objects settle) / ``stop_when()`` or
        :attr:`interrupted` (asked after every tick)."""
        start_wall = time.perf_counter()
        self.schedule.resume()  # the first tick now, not at a deadline from before set-up
        finished_at: float | None = None
        resets = self.resets
        success = False
        while True:
            tick = self.tick()
            if progress is not None:
                progress(tick)
            success = success or tick.state.success
            elapsed = self.ticks * self.dt
            if (tick.state.success and stop_on_success) or tick.state.failure:
                break
            if self.interrupted() or (stop_when is not None and stop_when()):
                break
            if tick.state.truncated or (max_seconds is not None and elapsed >= max_seconds):
                break
            if self.resets != resets:  # reset from a view or a listener: a new episode
                resets, finished_at = self.resets, None
            if self.source.finished:
                finished_at = elapsed if finished_at is None else finished_at
                if elapsed - finished_at >= tail_seconds:
                    break
        return self.summary(success, wall_s=time.perf_counter() - start_wall)

    def summary(self, success: bool, wall_s: float | None = None) -> TeleopSummary:
        """The episode so far, as the CLI reports it."""
        env = self.twin.env
        holds = {name: dict(by_reason) for name, by_reason in self.holds.items()}
        for name, n in getattr(self.twin, "step_limited", {}).items():
            if n:
                count_hold(holds, name, "step_limit", int(n))
        listener_errors = dict(self.listener_errors)
        for listener in self.listeners:
            if isinstance(listener, ThreadedListener) and listener.errors:
                name = listener_name(listener)
                listener_errors[name] = listener_errors.get(name, 0) + listener.errors
        return TeleopSummary(
            task=env.task.name,
            embodiment=env.embodiment.label,
            success=bool(success),
            frames_received=self.frames_received,
            frames_rejected=self.validator.rejected,
            commands_applied=self.twin.commands_applied,
            duration_s=self.ticks * self.dt,
            latency_ms=self.latencies_ms.percentiles(),
            rejected_by_reason={
                **self.validator.rejected_by_reason,
                **self.source.refused_connections(),
            },
            holds=holds,
            operator={name: asdict(op.stats) for name, op in self.operator.effectors.items()},
            ticks=self.ticks,
            loop_rate_hz=self.ticks / wall_s if wall_s else None,
            guard_blocks=dict(getattr(self.twin, "guard_blocks", {})),
            listener_errors=listener_errors,
            overruns=self.schedule.overruns,
            missed_ticks=self.schedule.missed_ticks,
            frames_superseded=self.frames_superseded
            + sum(getattr(getattr(self.source, "receiver", None), "superseded", {}).values()),
        )
