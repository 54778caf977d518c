"""The collision guard: commands into the table are refused, objects never block."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.twin.guard import CollisionGuard, GuardConfig
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand


@pytest.fixture(scope="module")
def twin():
    env = gym.make("beavr_sim/PickupBox-v0")
    twin = TwinInterface(env)
    twin.reset(seed=0)
    yield twin
    env.close()


def _into_table(twin) -> np.ndarray:
    """A full action whose arm reaches down through the table (found by sweeping the
    shoulder and elbow pitch)."""
    guard, q0 = twin.guard, twin.action.copy()
    sl = twin.slices["right"]
    for j2 in np.linspace(0.0, 2.0, 21):
        for j4 in np.linspace(0.0, 3.0, 31):
            q = q0.copy()
            q[sl.start + 1], q[sl.start + 3] = j2, j4
            verdict = guard.check(q, twin.env.data.qpos)
            if any("table" in a or "table" in b for a, b, _ in verdict.contacts):
                return q
    raise AssertionError("no arm configuration through the table found")


def test_home_and_objects_do_not_block(twin):
    verdict = twin.guard.check(twin.action, twin.env.data.qpos)
    assert verdict.ok and verdict.contacts == ()
    # Every geom is the robot's, the static scene's, or an object's (never guarded).
    model = twin.env.model
    owners = {twin.guard._owner[g] for g in range(model.ngeom)}
    assert owners == {"right", "static", None}
    box = [g for g in range(model.ngeom) if twin.guard._owner[g] is None]
    assert box, "the task's box should be an unguarded object"


def test_command_through_the_table_is_refused_and_robot_holds(twin):
    q_bad = _into_table(twin)
    before = twin.action.copy()
    sl = twin.slices["right"]
    cmd = JointCommand("right", q_bad[sl], t_source=0.0, t_receive=0.0)
    applied = twin.commands_applied
    state = twin.apply({"right": cmd})
    assert state.guard_blocked and state.guard_blocked_effectors == ("right",)
    np.testing.assert_array_equal(state.action, before)  # the refused target never applied
    assert twin.commands_applied == applied  # a refused command is not counted as applied
    assert twin.guard_blocks["right"] >= 1
    assert any("table" in a or "table" in b for a, b, _ in twin.last_refusal.contacts)
    # A safe command afterwards goes through again.
    ok = JointCommand("right", before[sl], t_source=0.0, t_receive=0.0)
    assert not twin.apply({"right": ok}).guard_blocked


def test_tolerance_is_respected(twin):
    q_bad = _into_table(twin)
    depth = max(d for _, _, d in twin.guard.check(q_bad, twin.env.data.qpos).contacts)
    lenient = CollisionGuard(
        twin.env.model,
        twin.env.embodiment,
        twin.env.joints,
        GuardConfig(tolerance=depth + 0.01, finger_tolerance=depth + 0.01),
    )
    assert lenient.check(q_bad, twin.env.data.qpos).ok
    with pytest.raises(ValueError, match="tolerance"):
        GuardConfig(tolerance=-1.0)
    with pytest.raises(ValueError, match="finger_tolerance"):
        GuardConfig(finger_tolerance=float("nan"))


def test_fingertips_pressing_on_the_table_are_allowed(twin):
    """A grasp near the table commands fingertips a few mm into it: not refused."""
    guard, model = twin.guard, twin.env.model
    fingers = [
        g for g in range(model.ngeom) if guard._tolerance[g] == guard.config.finger_tolerance
    ]
    arm = [g for g in range(model.ngeom) if guard._tolerance[g] == guard.config.tolerance]
    assert fingers and arm
    names = {guard._geom_names[g] for g in fingers}
    assert any("distal" in n for n in names) and not any("link" in n for n in names)


def test_arms_driven_into_each_other_are_refused():
    """Bimanual: the two arms swung towards each other collide; both commands are refused."""
    env = gym.make("beavr_sim/PickPlace-v0", embodiment="xarm7_leap_bimanual")
    try:
        twin = TwinInterface(env)
        twin.reset(seed=0)
        q0 = twin.action.copy()
        right, left = twin.slices["right"], twin.slices["left"]

        def arms_touch(v):
            return [c for c in v.contacts if {c[0][:4], c[1][:4]} == {"left", "righ"}]

        verdicts = []
        for yaw in np.linspace(0.0, 1.6, 17):
            q = q0.copy()
            q[right.start], q[left.start] = yaw, -yaw  # shoulders turn towards each other
            q[right.start + 1] = q[left.start + 1] = 0.0
            q[right.start + 3] = q[left.start + 3] = 1.0
            verdicts.append((yaw, twin.guard.check(q, twin.env.data.qpos)))
        touching = [(yaw, v) for yaw, v in verdicts if arms_touch(v)]
        assert touching, "the arms never met"
        yaw, verdict = touching[0]
        assert verdict.blocked == ("left", "right")
        assert verdicts[0][1].ok  # facing forward they are apart
        q = q0.copy()
        q[right.start], q[left.start] = yaw, -yaw
        q[right.start + 3] = q[left.start + 3] = 1.0
        q[right.start + 1] = q[left.start + 1] = 0.0
        commands = {
            name: JointCommand(name, q[sl], t_source=0.0, t_receive=0.0)
            for name, sl in twin.slices.items()
        }
        state = twin.apply(commands)
        assert state.guard_blocked_effectors == ("left", "right")
        np.testing.assert_array_equal(state.action, q0)
    finally:
        env.close()
