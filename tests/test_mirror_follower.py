"""The one mirror follower (:class:`beavr_sim.teleop.mirroring.MirrorFollower`) on a twin
stage's hooks, against a scripted twin and a recording mirror (no physics, no devices): what
each hook hands the mirror, the heartbeat, a new episode's joints, and a failing mirror."""

from __future__ import annotations

import numpy as np

from beavr_sim.teleop.mirroring import MirrorFollower
from beavr_sim.teleop.stages import TwinStage
from beavr_sim.twin.twin import CommandOutcome
from beavr_sim.wire.records import TwinState

N = 3  # joints


class ScriptedTwin:
    """A twin whose commands set the action and whose steps move its joints there."""

    def __init__(self):
        self.action = np.zeros(N)
        self.positions = np.zeros(N)
        self.applied_monotonic = 0.0

    def reset(self, seed=None, robot_qpos=None) -> np.ndarray:
        self.positions = np.full(N, 5.0) if robot_qpos is None else np.array(robot_qpos)
        self.action = self.positions.copy()
        return self.action.copy()

    def command(self, commands) -> CommandOutcome:
        self.action = np.asarray(commands["arm"], dtype=np.float64)
        return CommandOutcome(accepted=("arm",), blocked=("hand",))

    def step(self) -> TwinState:
        self.positions = self.action.copy()
        return TwinState(
            t=0.0,
            positions=self.positions.copy(),
            velocities=np.zeros(N),
            action=self.action.copy(),
            success=False,
            failure=False,
            terminated=False,
            truncated=False,
            guard_blocked_effectors=("hand",),
        )


class RecordingMirror:
    def __init__(self, fail: bool = False):
        self.submits: list[tuple[list, list, tuple]] = []
        self.fail = fail

    def submit(self, action, positions, refused=()) -> None:
        if self.fail:
            raise RuntimeError("the mirror is broken")
        self.submits.append((list(action), list(positions), tuple(refused)))


def test_follower_submits_each_command_a_heartbeat_and_starts_over_at_a_reset():
    twin, mirror = ScriptedTwin(), RecordingMirror()
    stage = TwinStage(twin)
    MirrorFollower(stage, mirror)
    stage.command({"arm": [1.0, 1.0, 1.0]}, latency=False)
    # the guarded action at once, with the twin's joints before the step
    assert mirror.submits == [([1.0] * N, [0.0] * N, ("hand",))]
    stage.step()  # a command came this period: no heartbeat
    assert len(mirror.submits) == 1
    stage.step()  # none this period: the same targets, the step's joints
    assert mirror.submits[-1] == ([1.0] * N, [1.0] * N, ("hand",))
    # a new episode: the next command carries the reset's joints, not the last step's
    stage.reset(0, robot_qpos=[2.0, 2.0, 2.0])
    stage.command({"arm": [3.0, 3.0, 3.0]}, latency=False)
    assert mirror.submits[-1] == ([3.0] * N, [2.0] * N, ("hand",))


def test_a_failing_mirror_is_counted_and_the_stage_goes_on():
    twin = ScriptedTwin()
    stage = TwinStage(twin)
    MirrorFollower(stage, RecordingMirror(fail=True))
    stage.command({"arm": [1.0, 1.0, 1.0]}, latency=False)
    stage.step()
    stage.step()
    # the command's submit and both heartbeats (a failed submit is no submit) raised
    assert stage.hook_errors == {"mirror": 3}
