"""A mirrored catch-up whose straight path the guard refuses goes around (hardware.detour).

Planner on the RX-1's scene (two arms, two LEAP hands, its body), and the mirror's catch-up
stepping along a planned detour: every target it makes passes the mirror's guard, no joint
moves faster than the catch-up cap, and it ends at the goal."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.hardware.detour import DetourConfig, joint_groups, plan_detour
from beavr_sim.hardware.guard import scene_guard
from beavr_sim.hardware.leap.config import LeapHandConfig
from beavr_sim.hardware.mirror import HardwareMirror
from beavr_sim.hardware.rig import DeviceEntry, RigConfig
from beavr_sim.hardware.xarm.config import XArmConfig


def blocked_pair(guard, qpos, home, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Two safe arm postures near home (seeded) whose straight path the guard refuses."""
    dt, guard.dt = guard.dt, None
    rng = np.random.default_rng(seed)
    arm = ~guard.hand_joints
    try:
        for _ in range(5000):
            a, b = (
                np.clip(home + rng.normal(0, 0.6, home.size) * arm, guard._lower, guard._upper)
                for _ in range(2)
            )
            if (
                guard.check(a, qpos).ok
                and guard.check(b, qpos).ok
                and not guard.check(b, qpos, a).ok
            ):
                return a, b
    finally:
        guard.dt = dt
    raise AssertionError("no blocked pair found")


def legs_pass(guard, qpos, start, waypoints) -> bool:
    dt, guard.dt = guard.dt, None
    try:
        q = start
        for w in waypoints:
            if not guard.check(w, qpos, q).ok:
                return False
            q = w
        return True
    finally:
        guard.dt = dt


@pytest.fixture(scope="module")
def rx1():
    return scene_guard("rx1")


@pytest.mark.parametrize("seed", [1, 2])
def test_planner_goes_around_a_refused_straight_path_on_the_rx1(rx1, seed):
    guard, qpos, home = rx1
    start, goal = blocked_pair(guard, qpos, home, seed)
    # bounded by the default check count alone: the same plan on a busy machine
    config = DetourConfig(budget_s=600)
    detour = plan_detour(guard, start, goal, qpos, config)
    assert detour.found, detour.reason
    assert detour.method in ("groups", "rrt")
    np.testing.assert_array_equal(detour.waypoints[-1], goal)
    assert legs_pass(guard, qpos, start, detour.waypoints)
    # The straight line is what the guard refuses (the plant: a planner that sends it).
    assert not legs_pass(guard, qpos, start, [goal])
    # Deterministic.
    again = plan_detour(guard, start, goal, qpos, config)
    assert [w.tolist() for w in again.waypoints] == [w.tolist() for w in detour.waypoints]


def test_rrt_alone_finds_a_way_and_a_budget_ends_it_with_a_reason(rx1, monkeypatch):
    guard, qpos, home = rx1
    start, goal = blocked_pair(guard, qpos, home, 1)
    monkeypatch.setattr("beavr_sim.hardware.detour._by_groups", lambda *a: None)
    detour = plan_detour(guard, start, goal, qpos, DetourConfig(max_checks=20000, budget_s=60))
    assert detour.found and detour.method == "rrt", detour.reason
    assert legs_pass(guard, qpos, start, detour.waypoints)
    none = plan_detour(guard, start, goal, qpos, DetourConfig(max_checks=3))
    assert not none.found and "no guarded path found within 3 checks" in none.reason


def test_groups_cover_every_joint_once(rx1):
    guard = rx1[0]
    idx = np.concatenate(joint_groups(guard))
    assert sorted(idx.tolist()) == list(range(guard.joints.size))


def test_mirror_catch_up_follows_the_detour_every_target_guarded():
    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    try:
        env.reset(seed=0)
        rig = RigConfig(
            (
                DeviceEntry("right_arm", "xarm7", "right", XArmConfig(host="127.0.0.1", port=9)),
                DeviceEntry("right_hand", "leap", "right", LeapHandConfig("/dev/null-c38")),
            )
        )
        mirror = HardwareMirror(rig, env.embodiment, env.joints, env.model, env.control_hz)
        guard = mirror.guard
        mirror.catch_up.qpos = env.data.qpos.copy()
        start, goal = blocked_pair(guard, mirror.catch_up.qpos, env.joints.home.astype(float), 3)
        interval = mirror._period  # one control period per step
        cap = np.asarray(mirror.catch_up.limit.max_velocity) * interval
        q, sent = start.copy(), []
        for _ in range(20000):
            if np.array_equal(q, goal):
                break
            target, verdict = mirror.catch_up.step(goal, q, interval)
            if verdict.ok:
                assert np.all(np.abs(target - q) <= cap * (1 + 1e-9))
                sent.append((q.copy(), target.copy()))
                q = target
            else:  # held: a refused step is never sent
                assert not mirror.detours or not mirror.detours[-1].found
        np.testing.assert_allclose(q, goal)
        assert mirror.detours and mirror.detours[-1].found
        guard.dt = None
        for a, b in sent:  # every target sent passes the guard along its step
            assert guard.check(b, mirror.catch_up.qpos, a).ok
    finally:
        env.close()
