"""The per-run decisions both layouts share (``teleop/runs.py``) and the keypoints message the
``--multiprocess`` recorder is fed (``wire/messages.py``), at unit level."""

from __future__ import annotations

import numpy as np
import pytest

from beavr_sim.datasets.episode_end import EpisodeEnd
from beavr_sim.teleop.runs import MAX_FAULTS_IN_A_ROW, RunPlan, SessionRuns
from beavr_sim.wire.hand import N_JOINTS, HandFrame
from beavr_sim.wire.messages import HandKeypointsMsg, MessageError, decode, encode


def _record(runs: SessionRuns, fault: str = "", success: bool = True) -> None:
    end = EpisodeEnd(fault=fault, task_success=success)
    runs.recorded(end, written=end.keep, duration_s=2.0, sync_s=0.5)


def test_a_traces_spoilt_episode_is_played_again_until_enough_are_saved():
    runs = SessionRuns(RunPlan(recording=True, episodes=2))
    assert runs.more() and runs.name() == "episode 1/2"
    _record(runs, fault="right_hand stopped answering")
    assert runs.more() and runs.name() == "episode 1/2"  # not counted: played again
    _record(runs)
    _record(runs)
    assert not runs.more()
    assert (runs.tally.runs, runs.saved, runs.tally.hardware_faults) == (3, 2, 1)
    assert [line["saved"] for line in runs.tally.lines()] == [False, True, True]


def test_episodes_spoilt_in_a_row_end_the_session():
    runs = SessionRuns(RunPlan(recording=True, episodes=5))
    for k in range(MAX_FAULTS_IN_A_ROW):
        assert not runs.too_many_faults()
        _record(runs, fault=f"fault {k}")
    assert runs.too_many_faults() and not runs.more()
    assert runs.stopped.startswith(f"{MAX_FAULTS_IN_A_ROW} episodes in a row")
    assert runs.stopped.endswith(f"fault {MAX_FAULTS_IN_A_ROW - 1}")


def test_repeat_and_the_sessions_time_bound_every_run():
    runs = SessionRuns(RunPlan(repeat=0, max_seconds=5.0))
    assert runs.episode_limit(None) == 5.0
    runs.played_run(True, 3.0)
    assert runs.more() and runs.episode_limit(10.0) == 2.0  # the time left, not the run's
    runs.played_run(False, 2.0)
    assert runs.time_up() and not runs.more()
    twice = SessionRuns(RunPlan(repeat=2))
    twice.played_run(True, 1.0)
    assert twice.more()
    twice.played_run(True, 1.0)
    assert not twice.more()
    assert twice.run_line(twice.tally.last) == "run 2: success, 1.0 s"


def test_a_rig_that_does_not_sync_ends_the_session_with_its_run_counted():
    runs = SessionRuns(RunPlan(recording=True, episodes=3))
    _record(runs)
    runs.sync_failed("right_arm failed and was not re-armed", sync_s=30.0)
    assert not runs.more()
    assert runs.stopped == "episode 2/3: right_arm failed and was not re-armed"
    last = runs.tally.report()["last"]
    assert last["saved"] is False and last["hardware_fault"] and last["sync_s"] == 30.0


def test_plans_are_checked():
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        RunPlan(recording=True, episodes=0)
    with pytest.raises(ValueError, match="max_seconds"):
        RunPlan(max_seconds=0.0)
    assert not RunPlan().several and RunPlan(repeat=0).several


def _frame(side: str, t: float = 1.0) -> HandFrame:
    joints = np.arange(N_JOINTS * 3, dtype=np.float64).reshape(N_JOINTS, 3) / 100
    tracked = np.ones(N_JOINTS, dtype=bool)
    tracked[5] = False
    joints[5] = np.nan
    return HandFrame(side=side, t_source=t, t_receive=t, joints=joints, tracked=tracked)


def test_the_keypoints_message_keeps_the_newest_frame_of_each_side():
    from beavr_sim.teleop.process_config import keypoints_from_wire, keypoints_to_wire

    frames = [_frame("right", 1.0), _frame("left", 1.0), _frame("right", 2.0)]
    msg = keypoints_to_wire(frames, ("right",), epoch=3, tick=7)
    back = decode(encode(msg), HandKeypointsMsg)
    assert (back.epoch, back.tick) == (3, 7)
    (frame,) = keypoints_from_wire(back)
    assert frame.side == "right" and frame.t_source == 2.0
    np.testing.assert_array_equal(frame.tracked, frames[2].tracked)
    np.testing.assert_array_equal(frame.joints[frame.tracked], frames[2].joints[frame.tracked])
    with pytest.raises(ValueError, match="one frame per side"):
        HandKeypointsMsg(frames=[back.frames[0], back.frames[0]])
    with pytest.raises(MessageError):
        decode(encode(msg)[:-3], HandKeypointsMsg)
