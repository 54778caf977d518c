"""A session's runs: the per-run decisions both layouts make, written once.

A session plays one run or several (a ``--repeat`` trace, recorded ``--episodes``), each from
a reset and, mirrored, from a synced rig. :class:`RunPlan` (frozen: passed whole to the
``--multiprocess`` twin) says how many and for how long; :class:`SessionRuns` counts them as
they end and decides whether another follows:

- recording: until ``episodes`` are saved; a trace's episode the hardware spoilt is played
  again (it does not count), but :data:`MAX_FAULTS_IN_A_ROW` spoilt in a row end the session;
- playing: ``repeat`` times (0: until the time is up);
- ``max_seconds`` bounds the whole session (every run's play time together);
- a rig that does not sync ends the session (its run is counted, with the fault).

Every run is counted in a :class:`~beavr_sim.teleop.pipeline.RunTally` (the summary's
``runs``, ``per_run``, ...), and its line for a person is :meth:`SessionRuns.run_line` /
:meth:`SessionRuns.episode_line`. The single-process session (``session.py``) and the twin
process (``twin_runs.py``) call these; neither decides on its own.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from beavr_sim.datasets.episode_end import EpisodeEnd
from beavr_sim.teleop.pipeline import RunRecord, RunTally

#: Recording: this many episodes in a row spoilt by the hardware end the session.
MAX_FAULTS_IN_A_ROW = 3


@dataclass(frozen=True)
class RunPlan:
    """How many runs a session plays. ``recording``: count saved episodes (``episodes`` of
    them), else plays (``repeat``; 0: until ``max_seconds`` or Ctrl-C); ``trace``: the source
    is a trace (replayed each run); ``max_seconds``: the whole session's play time (None: no
    bound)."""

    recording: bool = False
    episodes: int = 1
    repeat: int = 1
    trace: bool = True
    max_seconds: float | None = None

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.repeat < 0:
            raise ValueError(
                f"episodes must be >= 1 and repeat >= 0, got {self.episodes}, {self.repeat}"
            )
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise ValueError(f"max_seconds must be positive, got {self.max_seconds}")

    @classmethod
    def of(cls, options) -> RunPlan:
        """The plan of a :class:`~beavr_sim.teleop.session.SessionOptions`."""
        return cls(
            recording=options.record is not None,
            episodes=options.episodes,
            repeat=options.repeat,
            trace=options.source == "trace",
            max_seconds=options.max_seconds,
        )

    @property
    def several(self) -> bool:
        """More than one run may be played."""
        return (self.episodes if self.recording else self.repeat) != 1


def episode_seeds(seed: int | None, trace: bool) -> Callable[[int], int | None]:
    """Each recorded episode's seed by attempt: a trace plays its own layout (``seed``) every
    time; live episodes get seed, seed + 1, ... (a seed from the clock where none is given)."""
    if trace:
        return lambda attempt: seed
    first = int(time.time()) % 100_000 if seed is None else seed
    return lambda attempt: first + attempt


class SessionRuns:
    """The runs of a session so far and what follows; see the module docstring."""

    def __init__(self, plan: RunPlan):
        self.plan = plan
        self.tally = RunTally()
        #: Runs ended (recorded episodes: attempts, saved or not).
        self.attempts = 0
        self.saved = 0
        #: Recording: episodes the hardware spoilt, in all and in a row.
        self.faulty = 0
        self.in_a_row = 0
        #: Session time played (s): every run's, and idle time where the runner adds it.
        self.played = 0.0
        #: Why the session ended before its runs were all played ("" when it did not).
        self.stopped = ""
        #: Recording: what became of the last episode (``EpisodeEnd.outcome``; "" before one).
        self.last_outcome = ""

    # ------------------------------------------------------------------ time
    def remaining(self) -> float | None:
        """Session time left (s; None: no bound)."""
        if self.plan.max_seconds is None:
            return None
        return max(self.plan.max_seconds - self.played, 0.0)

    def time_up(self) -> bool:
        left = self.remaining()
        return left is not None and left <= 1e-9

    def episode_limit(self, episode_seconds: float | None) -> float | None:
        """The next run's time limit: the recording's ``episode_seconds`` and the time left."""
        limits = (s for s in (episode_seconds, self.remaining()) if s is not None)
        return min(limits, default=None)

    # ------------------------------------------------------------------ what follows
    def more(self) -> bool:
        """Whether another run follows (asked before each; the first always plays)."""
        if self.stopped:
            return False
        if self.plan.recording:
            episodes = self.plan.episodes
            trace_done = self.plan.trace and self.attempts - self.faulty >= episodes
            return self.saved < episodes and not trace_done
        if self.attempts == 0:
            return True
        repeat = self.plan.repeat
        return not (repeat and self.attempts >= repeat) and not self.time_up()

    def name(self) -> str:
        """The next (or current) run's name for a person: ``episode 2/3``, ``run 2``."""
        if self.plan.recording:
            return f"episode {self.saved + 1}/{self.plan.episodes}"
        return f"run {self.attempts + 1}"

    # ------------------------------------------------------------------ runs that ended
    def sync_failed(self, fault: str, sync_s: float | None) -> RunRecord:
        """The rig did not reach the next run's start: counted, and the session ends."""
        saved = False if self.plan.recording else None
        record = RunRecord(self.attempts + 1, False, 0.0, fault, saved=saved, sync_s=sync_s)
        self.stopped = f"{self.name()}: {fault}"
        self.tally.add(record)
        return record

    def played_run(
        self, success: bool, duration_s: float, fault: str = "", sync_s: float | None = None
    ) -> RunRecord:
        """A run without recording ended."""
        self.attempts += 1
        self.played += duration_s
        record = RunRecord(self.attempts, bool(success), duration_s, fault, sync_s=sync_s)
        self.tally.add(record)
        return record

    def recorded(
        self, end: EpisodeEnd, written: bool, duration_s: float, sync_s: float | None = None
    ) -> RunRecord:
        """A recorded episode ended as ``end`` decided (``written``: it is in the dataset)."""
        fault = end.fault
        self.attempts += 1
        self.played += duration_s
        self.saved += int(end.counts_as_saved(written))
        self.faulty += int(bool(fault))
        self.in_a_row = self.in_a_row + 1 if fault else 0
        self.last_outcome = end.outcome(written)
        record = RunRecord(
            self.attempts, bool(end.task_success), duration_s, fault, written, sync_s=sync_s
        )
        self.tally.add(record)
        return record

    def too_many_faults(self) -> bool:
        """Recording: :data:`MAX_FAULTS_IN_A_ROW` episodes in a row were spoilt by the
        hardware; the session ends (asked after the episode's other ends)."""
        if self.in_a_row < MAX_FAULTS_IN_A_ROW:
            return False
        last = self.tally.last.hardware_fault if self.tally.last is not None else ""
        self.stop(f"{self.in_a_row} episodes in a row spoilt by the hardware; the last: {last}")
        return True

    def stop(self, why: str) -> None:
        """End the session before its runs are played (``why``: its summary's
        ``stopped_early``)."""
        self.stopped = self.stopped or why

    # ------------------------------------------------------------------ lines
    @staticmethod
    def run_line(record: RunRecord) -> str:
        """A played run's line (stderr)."""
        fault = record.hardware_fault
        return (
            f"run {record.run}: {'success' if record.success else 'no success'}, "
            f"{record.duration_s:.1f} s" + (f"; HARDWARE FAULT: {fault}" if fault else "")
        )

    @staticmethod
    def episode_line(name: str, record: RunRecord, end: EpisodeEnd, written: bool, where: str):
        """A recorded episode's line (stderr); ``where``: e.g. ``"3 in D"``."""
        fault = record.hardware_fault
        return (
            f"{name}: {'success' if record.success else 'no success'}, "
            f"{record.duration_s:.1f} s, "
            + (f"HARDWARE FAULT: {fault}, " if fault else "")
            + f"{end.outcome(written)} ({where})"
        )
