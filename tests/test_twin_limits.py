"""The twin's last line: no joint command moves further in one control period than its speed
cap allows, whatever produced it; and the operator does not jump when the guard lets an
effector go again (issue 25)."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand


@pytest.fixture(scope="module")
def env():
    env = gym.make("beavr_sim/PickupBox-v0")
    yield env
    env.close()


def _command(name: str, q: np.ndarray) -> dict[str, JointCommand]:
    return {name: JointCommand(name, q, t_source=0.0, t_receive=0.0)}


@pytest.mark.parametrize("use_guard", [True, False])
@pytest.mark.parametrize("joint, what", [(0, "arm"), (10, "hand")])
def test_a_far_command_arrives_at_the_speed_cap(env, use_guard, joint, what):
    """A command 1 rad from the current one: each tick moves that joint by at most
    ``vmax * dt``, it arrives after ``ceil(1 / (vmax * dt))`` ticks, and each clamped tick is
    counted; the guard (when on) sees only the clamped steps and refuses none."""
    twin = TwinInterface(env, use_guard=use_guard)
    q0 = twin.reset(seed=0)
    sl = twin.slices["right"]
    i = sl.start + joint
    assert twin.hand_joints[i] == (what == "hand")
    vmax, dt = twin.max_velocity[i], twin.dt
    assert vmax == (8.0 if what == "hand" else math.pi)
    sign = 1.0 if q0[i] + 1.0 <= env.unwrapped.joints.upper[i] else -1.0
    goal = q0.copy()
    goal[i] += sign * 1.0
    ticks = math.ceil(1.0 / (vmax * dt))
    previous = q0
    for k in range(1, ticks + 1):
        state = twin.apply(_command("right", goal[sl]))
        assert not state.guard_blocked
        step = np.abs(state.action - previous)
        assert step[i] <= vmax * dt * (1 + 1e-12)
        assert np.all(np.delete(step, i) == 0.0)
        if k < ticks:
            assert step[i] == pytest.approx(vmax * dt)
        previous = state.action
    np.testing.assert_array_equal(previous, goal)
    assert twin.step_limited == {"right": ticks - 1}
    twin.apply(_command("right", goal[sl]))  # already there: nothing to clamp
    assert twin.step_limited == {"right": ticks - 1}


def test_a_mirrored_twin_steps_no_faster_than_the_rigs_devices(env):
    """``follow_speed_caps`` (a mirrored rig's device caps): a joint whose device is slower than
    the twin's own cap moves at the device's speed, so the hardware can follow every step; a
    faster device leaves the twin's cap as it was."""
    twin = TwinInterface(env)
    q0 = twin.reset(seed=0)
    sl = twin.slices["right"]
    i = sl.start  # the arm's first joint
    own = twin.max_velocity.copy()
    caps = own * 2.0  # faster devices: nothing changes ...
    caps[i] = math.pi / 2  # ... but one servo at pi/2 rad/s
    twin.follow_speed_caps(caps)
    assert twin.max_velocity[i] == math.pi / 2
    np.testing.assert_array_equal(np.delete(twin.max_velocity, i), np.delete(own, i))
    sign = 1.0 if q0[i] + 0.5 <= env.unwrapped.joints.upper[i] else -1.0
    goal = q0.copy()
    goal[i] += sign * 0.5
    state = twin.apply(_command("right", goal[sl]))
    assert abs(state.action[i] - q0[i]) == pytest.approx(math.pi / 2 * twin.dt)


def test_the_step_limit_leaves_corrupt_targets_to_the_guard(env):
    """A non-finite target, or one past the joint's range, is refused whole by the guard (the
    robot does not move towards it); with the guard off, the range is clamped like speed."""
    twin = TwinInterface(env)
    q0 = twin.reset(seed=0)
    sl = twin.slices["right"]
    upper = env.unwrapped.joints.upper
    for joint, value, rule in ((2, np.nan, "non-finite"), (3, upper[3] + 0.3, "joint limit")):
        q = q0[sl].copy()
        q[joint] = value
        state = twin.apply(_command("right", q))
        assert state.guard_blocked_effectors == ("right",)
        assert twin.last_refusal.reasons["right"].startswith(rule)
        np.testing.assert_array_equal(state.action, q0)
    assert twin.step_limited == {}
    unguarded = TwinInterface(env, use_guard=False)
    q0 = unguarded.reset(seed=0)
    q = q0[sl].copy()
    q[3] = upper[3] + 0.3
    state = unguarded.apply(_command("right", q))
    assert state.action[sl.start + 3] == pytest.approx(q0[sl.start + 3] + math.pi / 30)
    assert unguarded.step_limited == {"right": 1}


def test_release_after_a_forced_guard_hold_does_not_jump(pickup_box_with_forced_hold):
    """Issue 25 item 2: the PickupBox trace with the guard refusing the right effector for
    1 s mid-grasp. While held, the operator is resynced to the held action, so when the hold
    ends no command (what the operator sends, before the twin's step limit) moves any joint
    further than its speed cap allows in one tick, and the step limit never has to act."""
    t0, t1 = 2.5, 3.5  # the hand closes on the box, the arm moving
    loop, _ = pickup_box_with_forced_hold(t0, t1)
    twin, guard = loop.twin, loop.twin.guard
    sl = twin.slices["right"]
    cap = guard.max_velocity[sl] * guard.dt * (1 + 1e-9)
    jumps, held = [], []
    previous = twin.action.copy()

    def watch(tick):
        nonlocal previous
        cmd = tick.commands.get("right")
        if cmd is not None and not cmd.hold:
            jumps.append(np.abs(cmd.positions - previous[sl]) / cap)
        held.append("right" in tick.state.guard_blocked_effectors)
        previous = tick.state.action.copy()

    loop.listeners.append(watch)
    summary = loop.run()
    assert sum(held) == pytest.approx(30, abs=1), "the forced hold did not last 1 s"
    release = held.index(True) + sum(held)
    assert not held[release]
    worst = np.max(jumps, axis=0)
    assert worst.max() <= 1.0, f"a command jumped {worst.max():.2f} x the step cap"
    assert twin.step_limited == {}
    assert summary.success
