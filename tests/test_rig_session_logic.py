"""The session's rig logic against a small fake mirror: the per-frame check of recorded state
(:class:`~beavr_sim.datasets.recorder.HardwareWatch`), the sync before an episode
(:class:`~beavr_sim.teleop.session.HardwareSync`), the bounded latency log and the CLI's
hardware outcome. The whole sessions on the emulated rig are in ``test_rig_session.py``."""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from beavr_sim.bench.soak import rss_mb, status_fields
from beavr_sim.datasets.recorder import FollowLimits, HardwareWatch
from beavr_sim.hardware.mirror import Reading, WriteLog
from beavr_sim.teleop.__main__ import hardware_outcome
from beavr_sim.teleop.mirroring import RigSync
from beavr_sim.teleop.pipeline import LatencyLog, RunRecord, RunTally, TeleopSummary
from beavr_sim.teleop.session import HardwareSync, ProgressLine, SessionOptions, build_loop


class State(enum.Enum):
    FOLLOWING = "following"
    HOLDING = "holding"
    OUTAGE = "outage"
    FAILED = "failed"


@dataclass(frozen=True)
class Device:
    name: str
    state: State
    reason: str = ""
    detail: str = ""


@dataclass(frozen=True)
class Health:
    live: bool
    devices: tuple
    episode_faults: tuple = ()


@dataclass
class FakeMirror:
    """What the session uses of ``HardwareMirror``: in sync after ``sync_after`` polls."""

    sync_after: int = 3
    failed: list = field(default_factory=list)
    health_now: Health = field(
        default_factory=lambda: Health(True, (Device("arm", State.FOLLOWING),))
    )
    begun: list = field(default_factory=list)
    polls: int = 0
    estopped: bool = False

    fixtures: list = field(default_factory=list)

    def begin_episode(self, q_start, fixtures=None) -> None:
        self.begun.append(np.array(q_start))
        self.fixtures.append(fixtures)
        self.polls = 0

    def in_sync(self) -> bool:
        self.polls += 1
        return self.polls > self.sync_after

    @property
    def failed_devices(self) -> list:
        return list(self.failed)

    def health(self) -> Health:
        return self.health_now


LIMITS = FollowLimits(np.array([0.3, 0.3, 0.8, np.inf]), 0.5, ("j1", "j2", "leap_0", "body"))


def _fresh() -> Reading:
    """A reading taken just now (the watch's checks here pass the state themselves)."""
    return Reading(np.zeros(4), time.monotonic(), "arm")


def _watch(health: Health) -> HardwareWatch:
    return HardwareWatch(_fresh, lambda: health, LIMITS, fps=30)


def test_watch_passes_a_state_that_follows():
    watch = _watch(Health(True, ()))
    watch.begin()
    for k in range(60):
        action = np.array([0.05 * k, -0.05 * k, 0.02 * k, 9.0])
        state = action - np.array([0.05, -0.05, 0.02, 0.0])  # one period behind
        assert watch.check(state, action) == ""
    assert watch.fault == "" and 0 < watch.max_gap_rad < 0.3


def test_watch_finds_a_frozen_state_after_the_window():
    """The bug of issue 38 item 1: the measured arm holds while the action moves on."""
    watch = _watch(Health(True, ()))
    watch.begin()
    frozen = np.zeros(4)
    faults = [watch.check(frozen, np.array([0.1 * k, 0.0, 0.0, 0.0])) for k in range(40)]
    first = next(i for i, f in enumerate(faults) if f)
    # 0.3 rad is passed at k = 4; the fault comes after more than 0.5 s (15 frames) beyond.
    assert 4 + 15 <= first <= 4 + 17, first
    assert "j1" in watch.fault and "limit 0.3" in watch.fault
    watch.begin()
    assert watch.fault == ""


def test_watch_reports_a_device_that_is_not_live():
    health = Health(False, (Device("right_hand", State.HOLDING, detail="no fresh command"),))
    watch = _watch(health)
    watch.begin()
    fault = watch.check(np.zeros(4), np.zeros(4))
    assert fault == "right_hand holding (no fresh command)" == watch.fault
    faulted = Health(True, (), episode_faults=("right_arm diverged 0.4 rad", "later"))
    watch = _watch(faulted)
    watch.begin()
    assert watch.check(np.zeros(4), np.zeros(4)) == "right_arm diverged 0.4 rad"
    # The health part alone (what LeRobot's robot asks before it observes): no frame taken.
    assert _watch(health).health_fault() == "right_hand holding (no fresh command)"
    assert _watch(faulted).health_fault() == "right_arm diverged 0.4 rad"
    assert _watch(Health(True, ())).health_fault() == ""
    # Waiting for commands (LeRobot's robot, before a frame's command): a command-timeout
    # hold is live then; any other hold is not, and an episode fault never is.
    waiting = Health(False, (Device("right_arm", State.HOLDING, "TIMEOUT", "no fresh command"),))
    assert _watch(waiting).health_fault(waiting_for_commands=True) == ""
    assert _watch(waiting).health_fault() == "right_arm holding (no fresh command)"
    assert _watch(health).health_fault(waiting_for_commands=True) == (
        "right_hand holding (no fresh command)"
    )
    assert _watch(faulted).health_fault(waiting_for_commands=True) == "right_arm diverged 0.4 rad"


def test_watch_observes_the_reading_and_keeps_its_age():
    """The frame's state is the mirror's reading; the oldest reading's age over the episode is
    kept (reported as ``max_state_age_s``), infinite for a device never read."""
    t_read = 100.0
    reading = Reading(np.array([0.1, 0.2, 0.3, 0.0]), t_read, "right_hand")
    watch = HardwareWatch(lambda: reading, lambda: Health(True, ()), LIMITS, fps=30)
    watch.begin()
    state = watch.observe(now=t_read + 0.45)
    np.testing.assert_array_equal(state, reading.q)
    assert watch.check(state, state) == "" and watch.max_reading_age_s == pytest.approx(0.45)
    watch.observe(now=t_read + 0.2)  # a younger reading does not lower the episode's worst
    assert watch.max_reading_age_s == pytest.approx(0.45)
    watch.begin()
    assert watch.max_reading_age_s == 0.0
    never = HardwareWatch(
        lambda: Reading(np.zeros(4), -math.inf, "right_arm"), lambda: Health(True, ()), LIMITS, 30
    )
    never.begin()
    never.observe()
    assert never.max_reading_age_s == math.inf


def test_follow_limits_are_checked():
    with pytest.raises(ValueError, match="one per joint"):
        FollowLimits(np.array([0.3]), 0.5, ("a", "b"))
    with pytest.raises(ValueError, match="positive"):
        FollowLimits(np.array([0.0]), 0.5, ("a",))


@pytest.fixture
def loop():
    options = SessionOptions(
        task="pickup_box", source="trace", viser=False, headless=True, progress=False
    )
    loop = build_loop(options)
    yield loop
    loop.twin.env.close()


def test_sync_ticks_without_consuming_the_trace_then_resets(loop):
    mirror = FakeMirror(sync_after=5)
    sync = HardwareSync(loop, mirror, ProgressLine(loop, enabled=False), timeout_s=60)
    loop.listeners.append(sync)
    source = loop.source
    home = loop.twin.action.copy()
    resets = loop.resets
    assert sync.run() == ""
    assert len(mirror.begun) == 1 and np.array_equal(mirror.begun[0], home)
    assert loop.source is source and source._next == 0  # no frame taken meanwhile
    assert loop.frames_received == 0
    assert loop.resets == resets + 1 and loop.ticks == 0  # the seeded start again
    assert not loop.operator.paused and sync.synced == 1
    summary = loop.run(max_seconds=1.0, stop_on_success=False)
    assert summary.frames_received > 0  # the trace plays from its start


def test_an_unseeded_episode_keeps_its_layout_through_the_sync(loop):
    """A session without a seed (a live headset's): the episode the rig syncs to and the one
    it then plays are the same layout, so the mirror's guard was given this episode's
    fixtures (before: the reset after the sync drew a new layout, the fixture up to 28 cm
    from where the guard had it)."""
    mirror = FakeMirror(sync_after=3)
    sync = HardwareSync(loop, mirror, ProgressLine(loop, enabled=False), timeout_s=60)
    loop.listeners.append(sync)
    data = loop.twin.env.data
    for _ in range(3):
        loop.reset(None)
        assert isinstance(loop.seed, int)
        at_sync_start = data.mocap_pos.copy()
        assert sync.run() == ""
        np.testing.assert_array_equal(mirror.fixtures[-1].mocap_pos, at_sync_start)
        np.testing.assert_array_equal(data.mocap_pos, at_sync_start)  # the episode's layout
    assert len({tuple(f.mocap_pos.ravel()) for f in mirror.fixtures}) > 1  # drawn per reset


def test_sync_times_out_or_ends_on_a_failed_device(loop):
    clock = [0.0]

    def tick_clock() -> float:
        clock[0] += 0.5
        return clock[0]

    stuck = FakeMirror(sync_after=10**9)
    stuck.health_now = Health(False, (Device("right_arm", State.HOLDING, detail="e-stop"),))
    sync = HardwareSync(loop, stuck, ProgressLine(loop, enabled=False), 3.0, clock=tick_clock)
    loop.listeners.append(sync)
    fault = sync.run()
    assert "within 3 s" in fault and "right_arm holding (e-stop)" in fault
    assert sync.progress.status.startswith("HARDWARE FAULT")
    loop.listeners.remove(sync)
    # A device in an outage may come back: the sync waits for it (here: until the timeout).
    out = FakeMirror(sync_after=10**9, failed=["right_hand"])
    out.health_now = Health(False, (Device("right_hand", State.OUTAGE, detail="reconnecting"),))
    sync = HardwareSync(loop, out, ProgressLine(loop, enabled=False), 3.0, clock=tick_clock)
    loop.listeners.append(sync)
    assert "within 3 s" in sync.run()
    loop.listeners.remove(sync)
    # A failed one (not re-armed, nobody at the keyboard) ends the sync at once.
    dead = FakeMirror(sync_after=10**9, failed=["right_hand"])
    dead.health_now = Health(False, (Device("right_hand", State.FAILED, detail="no answer"),))
    sync = HardwareSync(loop, dead, ProgressLine(loop, enabled=False), 30.0)
    loop.listeners.append(sync)
    assert sync.run().startswith("right_hand failed and was not re-armed")


def test_rig_sync_alone_is_what_both_layouts_poll():
    """``RigSync`` (the multiprocess twin polls it without a loop): None until it ends, then
    "" once in sync (counted) or the fault; a timeout that is not positive is refused."""
    clock = [0.0]
    mirror = FakeMirror(sync_after=2)
    sync = RigSync(mirror, 1.0, clock=lambda: clock[0])
    assert sync.poll() is None and not sync.syncing  # nothing begun
    sync.begin(np.zeros(3), fixtures=None)
    assert sync.poll() is None and sync.poll() is None and sync.syncing
    clock[0] = 0.25
    assert sync.poll() == "" and sync.synced == 1 and sync.last_sync_s == 0.25
    sync.begin(np.zeros(3), fixtures=None)
    clock[0] = 2.0
    assert "within 1 s" in sync.poll() and not sync.syncing and sync.synced == 1
    with pytest.raises(ValueError, match="positive"):
        RigSync(mirror, 0.0)


def test_latency_log_is_bounded_and_reads_like_a_list():
    log = LatencyLog(recent=8, sample=16)
    for v in range(100):
        log.append(float(v))
    assert len(log) == 100
    assert log[-3:] == [97.0, 98.0, 99.0] and log[95:] == [95.0, 96.0, 97.0, 98.0, 99.0]
    assert log[0:] == [float(v) for v in range(92, 100)]  # only what the ring holds
    p = log.percentiles()
    assert p["n"] == 100 and 0 <= p["p50"] <= 99
    small = LatencyLog(recent=8, sample=16)
    for v in (1.0, 2.0, 3.0):
        small.append(v)
    assert small.percentiles() == {"p50": 2.0, "p99": pytest.approx(2.98), "n": 3}
    small.clear()
    assert len(small) == 0 and small[-5:] == []


def test_bounded_statistics_are_resident_from_the_start():
    """Filling a latency log or a device's write log does not grow the process: their buffers
    are written through at construction (np.zeros' pages became resident only as each was
    first written, which a soak saw as a slope of ~1 MB/h for the first hour)."""
    n = 1 << 19  # 4 MB per buffer
    for log, add in (
        (LatencyLog(recent=n, sample=n), lambda log, v: log.append(v)),
        (WriteLog(size=n), lambda log, v: log.add(v, v)),
    ):
        before = rss_mb()
        for v in range(n):
            add(log, float(v))
        assert rss_mb() - before < 2.0, type(log).__name__  # was ~8 MB: every page touched


def test_summary_counts_runs_and_the_cli_outcome():
    summary = TeleopSummary("T", "E", False, 0, 0, 0, 1.0, {})
    tally = RunTally()
    tally.add(RunRecord(1, True, 9.0))
    tally.add(RunRecord(2, True, 9.0, hardware_fault="right_arm failed"))
    tally.add(RunRecord(3, False, 2.5))
    tally.add(RunRecord(4, True, 9.0, saved=False))  # recorded, discarded: not a success
    summary.count_runs(tally)
    report = summary.to_dict()
    assert report["runs"] == 4 and report["successes"] == 1 and report["hardware_faults"] == 1
    assert report["per_run_dropped"] == 0 and len(report["per_run"]) == 4
    assert report["run_totals"]["duration_s"] == 29.5
    assert report["per_run"][1] == {
        "run": 2,
        "success": False,  # the twin finished; the rig did not follow all along
        "task_success": True,
        "duration_s": 9.0,
        "hardware_fault": "right_arm failed",
    }
    assert [r["success"] for r in report["per_run"]] == [True, False, False, False]
    assert hardware_outcome(report) == (0, "")
    report["failed_devices"] = ["right_arm"]
    report["hardware"] = {"right_arm": {"reason": "no answer within 5 s"}}
    code, line = hardware_outcome(report)
    assert code == 4 and "right_arm" in line and "no answer within 5 s" in line
    code, line = hardware_outcome({"stopped_early": "episode 2/3: not in sync"})
    assert code == 5 and "not in sync" in line


def test_a_long_sessions_run_lines_stay_bounded():
    """A day of ``--repeat`` runs keeps the first and the last ``kept`` runs' lines and counts
    every run (the lines were kept whole: one per run, for ever)."""
    tally = RunTally(kept=3)
    for run in range(1, 1001):
        tally.add(RunRecord(run, run % 2 == 0, 2.0, sync_s=0.5 if run == 7 else 0.25))
    summary = TeleopSummary("T", "E", False, 0, 0, 0, 1.0, {})
    summary.count_runs(tally)
    report = summary.to_dict()
    assert [line["run"] for line in report["per_run"]] == [1, 2, 3, 998, 999, 1000]
    assert report["runs"] == 1000 and report["successes"] == 500
    assert report["per_run_kept"] == 3 and report["per_run_dropped"] == 994
    totals = report["run_totals"]
    assert totals["duration_s"] == 2000.0 and totals["longest_s"] == 2.0
    assert totals["slowest_sync_s"] == 0.5 and totals["mean_sync_s"] == 0.25
    with pytest.raises(ValueError, match="kept must be >= 1"):
        RunTally(kept=0)


def test_watch_allows_the_devices_lag_but_not_a_frozen_state():
    """Within ``lag_s`` a device may trail its commands (judged against the commands of that
    stretch, as the mirror judges what it sent); a frozen one still fails."""
    limits = FollowLimits(np.array([0.3]), 0.5, ("j1",), lag_s=0.25)
    lagging = HardwareWatch(_fresh, lambda: Health(True, ()), limits, fps=30)
    lagging.begin()
    ramp = [np.array([0.1 * k]) for k in range(60)]
    assert not any(lagging.check(ramp[max(0, k - 5)], ramp[k]) for k in range(60))
    frozen = HardwareWatch(_fresh, lambda: Health(True, ()), limits, fps=30)
    frozen.begin()
    assert any(frozen.check(np.zeros(1), ramp[k]) for k in range(60))


def test_the_soak_splits_resident_memory_into_anonymous_and_file_backed():
    """The soak's split reads ``/proc/<pid>/status``: VmRSS is the sum of its parts, a gone
    process reads as nothing."""
    fields = status_fields()
    assert fields["VmRSS"] == fields["RssAnon"] + fields["RssFile"] + fields["RssShmem"]
    assert fields["Threads"] >= 1
    assert status_fields(2**22 + 12345) == {} and rss_mb(2**22 + 12345) is None
