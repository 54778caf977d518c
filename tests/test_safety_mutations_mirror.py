"""The mirror's own guarded catch-up, judged by what the emulated arm received.

When the devices are further from the twin than one period's motion (after a hold, a release,
a reset) the mirror makes its own targets on the straight line to the twin's; its guard checks
each along its path, and a refused one is not sent: the mirror plans a way around
(:mod:`beavr_sim.hardware.detour`), or, with none found, the device holds short of it. These
tests drive a catch-up whose straight path crosses the table or Tape's box (where this episode's
reset put it: :meth:`~beavr_sim.hardware.mirror.HardwareMirror.begin_episode` tells the
mirror's guard), and check every target the emulated
xArm received (:attr:`~beavr_sim.hardware.rig.EmulatedRig.received`) against a guard.
"""

from __future__ import annotations

import dataclasses
import math
import time

import gymnasium as gym
import numpy as np
import pytest

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.hardware.detour import DetourConfig
from beavr_sim.hardware.mirror import Fixtures, HardwareMirror
from beavr_sim.hardware.rig import EmulatedRig
from beavr_sim.twin.guard import CollisionGuard

ARM = slice(0, 7)


class FakeClock:
    """The mirror's clock for submit spacing: one control period per submit, however slowly
    this machine runs the test (the catch-up's progress per submit is then fixed)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _either_side(guard: CollisionGuard, qpos: np.ndarray, into: np.ndarray):
    """Two safe configurations whose straight joint path passes through ``into`` (an unsafe
    one): its forearm rolled both ways until each end is clear, and 0.4 rad further (so that
    a catch-up from either end moves before it meets the obstacle)."""
    for roll in np.linspace(0.2, 2.0, 19):
        a, b = into.copy(), into.copy()
        a[4] -= roll + 0.4
        b[4] += roll + 0.4
        if all(guard.check(q, qpos).ok for q in (a, b, a + (into - a) * 0.2, b + (into - b) * 0.2)):
            assert not guard.check(b, qpos, previous=a).ok  # the path between them is not
            return a, b
    raise AssertionError("no roll clears the hand on both sides")


def _lowered(guard: CollisionGuard, qpos: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``q`` with the shoulder pitched down until the guard refuses it, then 0.05 rad more."""
    step = np.eye(q.size)[1]
    into = next(
        q + step * a for a in np.linspace(0.0, 1.0, 101) if not guard.check(q + step * a, qpos).ok
    )
    return into + step * 0.05


def _either_side_of_the_table(env, guard: CollisionGuard) -> tuple[np.ndarray, np.ndarray]:
    """The hand lowered from home into the table, then rolled clear both ways."""
    qpos = env.data.qpos
    return _either_side(guard, qpos, _lowered(guard, qpos, env.joints.home.astype(np.float64)))


def _catch_up(
    env, start: np.ndarray, goal: np.ndarray, detour: bool = True
) -> tuple[np.ndarray, dict]:
    """The emulated arm holds at ``start`` and the twin stands at ``goal`` (its heartbeats,
    one control period apart, until the mirror's target reaches it, then 20 more, or until it
    has held still for a straight catch-up's worth; at most 10 straight catch-ups' worth):
    every arm target the emulator received, and the arm's summary.
    ``detour=False``: the mirror's planner gets no budget (it finds no way around)."""
    rig = EmulatedRig(env.embodiment, env.joints, q_start=start)
    try:
        mirror_config = dataclasses.replace(
            rig.config.mirror, arm_catch_up_speed=1.0, arm_divergence_rad=3.0
        )
        config = dataclasses.replace(rig.config, mirror=mirror_config)
        clock = FakeClock()
        period = 1.0 / env.control_hz
        mirror = HardwareMirror(
            config, env.embodiment, env.joints, env.model, env.control_hz, clock=clock
        )
        if not detour:
            mirror.catch_up.config = DetourConfig(max_checks=1)
        try:
            measured = mirror.connect()
            np.testing.assert_allclose(measured[ARM], start[ARM], atol=1e-4)
            mirror.start(measured)
            mirror.begin_episode(measured, Fixtures.of(env.data))  # this episode's fixtures
            distance = float(np.abs(goal - measured).max())
            ticks = math.ceil(distance / (mirror_config.arm_catch_up_speed * period))
            after, still, last = 20, 0, None
            for _ in range(10 * ticks):
                clock.t += period
                mirror.submit(goal, goal)
                time.sleep(period)  # paced like the twin (nothing is counted against it)
                target = mirror.dispatched.target
                if np.array_equal(target, goal):
                    after -= 1
                    if not after:
                        break
                # Held short: the target has not moved for a whole straight catch-up's time
                # (the catch-up plans once per goal; held, it holds for good).
                still = still + 1 if last is not None and np.array_equal(target, last) else 0
                last = target.copy()
                if still >= ticks:
                    break
            summary = mirror.summary()["right_arm"]
        finally:
            mirror.close()
    finally:
        rig.close()
    targets = np.array([q for _, q in rig.received["right_arm"]], dtype=np.float64)
    return targets, summary


def _check_received(guard, qpos, start, goal, targets, summary, reached: bool) -> None:
    """Every target the arm received is safe, and so is the way from the one before; the arm
    caught up towards the twin: ``reached``, going around (the straight path is refused), else
    it stopped short (never reached the goal)."""
    assert len(targets) and summary["catch_up_steps"] > 0 and summary["errors"] == 0
    full = np.tile(goal, (len(targets), 1))
    full[:, ARM] = targets
    unsafe = [
        (k, verdict.reason())
        for k, verdict in (
            (k, guard.check(q, qpos, previous=full[k - 1] if k else None))
            for k, q in enumerate(full)
        )
        if not verdict.ok
    ]
    assert not unsafe, f"{len(unsafe)} targets the arm received are unsafe: {unsafe[:2]}"
    assert np.abs(targets[-1] - start[ARM]).max() > 0.05
    assert not guard.check(goal, qpos, start).ok  # the straight way is refused
    if reached:
        np.testing.assert_allclose(targets[-1], goal[ARM], atol=1e-4)
    else:
        assert np.abs(targets[-1] - goal[ARM]).max() > 0.1


@pytest.mark.parametrize(
    ("direction", "detour"), [("a_to_b", True), ("b_to_a", True), ("a_to_b", False)]
)
def test_a_catch_up_whose_path_crosses_the_table_goes_around_or_stops_short(direction, detour):
    """The arm holds at one end, the twin stands at the other: the mirror's guard refuses the
    straight catch-up into the table, and the mirror goes around it (a planned detour) to the
    twin's pose; with no way found it holds short of the table. Every target the emulated arm
    received passes the guard (as a configuration and along the path from the one before)."""
    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    try:
        env.reset(seed=0)
        guard = CollisionGuard(env.model, env.embodiment, env.joints)
        qpos = env.data.qpos.copy()
        a, b = _either_side_of_the_table(env, guard)
        start, goal = (a, b) if direction == "a_to_b" else (b, a)
        targets, summary = _catch_up(env, start, goal, detour)
    finally:
        env.close()
    _check_received(guard, qpos, start, goal, targets, summary, reached=detour)


def test_a_catch_up_whose_path_crosses_a_fixture_goes_around_it():
    """Tape's box where the reset put it (away from its default pose): a catch-up whose path
    crosses it goes around it, as for the table (the detour planned against this episode's
    fixtures)."""
    env = gym.make("beavr_sim/Tape-v0").unwrapped
    try:
        env.reset(seed=0)
        data, model, joints = env.data, env.model, env.joints
        box_xy = data.mocap_pos[0, :2].copy()
        assert np.linalg.norm(box_xy - model.body_pos[model.body("box").id][:2]) > 0.15
        guard = CollisionGuard(model, env.embodiment, joints)
        guard.set_fixtures(data.mocap_pos, data.mocap_quat)
        qpos = data.qpos.copy()
        # The base turned towards the box, the elbow opened to its distance: the hand
        # lowered into it.
        into = None
        for elbow in np.linspace(0.0, 0.8, 17):
            q = joints.home.astype(np.float64)
            q[0] += math.atan2(box_xy[1], box_xy[0])
            q[3] += elbow
            lowered = _lowered(guard, qpos, q)
            if any("box/geom" in (a, b) for a, b, _ in guard.check(lowered, qpos).contacts):
                into = lowered
                break
        assert into is not None, "no elbow setting lowers the hand into the box"
        a, b = _either_side(guard, qpos, into)
        targets, summary = _catch_up(env, a, b)
    finally:
        env.close()
    _check_received(guard, qpos, a, b, targets, summary, reached=True)
