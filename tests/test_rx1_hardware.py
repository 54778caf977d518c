"""The RX-1 rig: Feetech arms and body and LEAP hands, emulated, mirrored through the guard."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import pytest
from waiting import wait_until

import beavr_sim.envs  # noqa: F401  (registers the envs)
from beavr_sim.hardware.feetech.config import GROUPS
from beavr_sim.hardware.mirror import HardwareMirror
from beavr_sim.hardware.rig import EmulatedRig, RigConfig, joint_names_of
from beavr_sim.robots import RX1_ARM, make_embodiment
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand

#: Half a servo count of a direct (gear 1) joint, in joint radians: the most a joint read back
#: differs from its target by rounding (a geared joint's count is three times finer).
HALF_COUNT = np.pi / 2048 * 0.51


def test_servo_table_drives_exactly_the_model_joints():
    embodiment = make_embodiment("rx1")
    for side in ("right", "left"):
        assert tuple(s.joint for s in GROUPS[f"{side}_arm"]) == RX1_ARM.joints
    body = tuple("body/" + s.joint for s in GROUPS["body"])
    assert body == embodiment.body_joints


def test_rig_files_name_groups_that_match_the_effector():
    embodiment = make_embodiment("rx1")
    good = RigConfig.from_dict(
        {
            "devices": [
                {"name": "r", "kind": "feetech", "effector": "right", "group": "right_arm",
                 "port": "/dev/null"},
                {"name": "b", "kind": "feetech", "effector": "body", "group": "body",
                 "port": "/dev/null"},
            ]
        }
    )  # fmt: skip
    good.check_embodiment(embodiment)
    assert [d.part for d in good.devices] == ["arm", "body"]
    assert joint_names_of(good.devices[1], embodiment) == embodiment.body_joints
    wrong_side = RigConfig.from_dict(
        {"devices": [{"name": "r", "kind": "feetech", "effector": "right", "group": "left_arm",
                      "port": "/dev/null"}]}
    )  # fmt: skip
    with pytest.raises(ValueError, match="must be right_arm"):
        wrong_side.check_embodiment(embodiment)
    with pytest.raises(ValueError, match="has none"):
        RigConfig.from_dict(
            {"devices": [{"name": "b", "kind": "feetech", "effector": "body", "group": "body",
                          "port": "/dev/null"}]}
        ).check_embodiment(make_embodiment("xarm7_leap_right"))  # fmt: skip
    with pytest.raises(KeyError, match="Valid feetech settings"):
        RigConfig.from_dict(
            {"devices": [{"name": "r", "kind": "feetech", "effector": "right", "grup": "x"}]}
        )


def test_rx1_mirrors_to_emulated_feetech_and_leap_through_the_guard():
    """Every device connects at the twin's pose, follows its effector; the body holds; a
    command the twin's guard refuses (an arm into the chest) never reaches a servo."""
    env = gym.make("beavr_sim/PickPlace-v0", embodiment="rx1").unwrapped
    rig = EmulatedRig(env.embodiment, env.joints)
    try:
        twin = TwinInterface(env)
        twin.reset(seed=0)
        mirror = HardwareMirror(rig.config, env.embodiment, env.joints, env.model, env.control_hz)
        q = mirror.connect()
        np.testing.assert_allclose(q, env.joints.home, atol=HALF_COUNT)
        twin.reset(seed=0, robot_qpos=q)
        mirror.start(twin.action)
        target = twin.action.copy()
        left = twin.slices["left"]
        roll = left.start + 1  # left shoulder_roll: towards the body
        refused = 0
        for _ in range(40):
            target[left.start] += 0.01  # the left shoulder pitch turns, slowly
            target[roll] -= 0.04
            command = {n: JointCommand(n, target[sl], 0.0, 0.0) for n, sl in twin.slices.items()}
            state = twin.apply(command)
            refused += "left" in state.guard_blocked_effectors
            if "left" in state.guard_blocked_effectors:
                target[left] = state.action[left]  # the operator resyncs to the held pose
            mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
            time.sleep(1 / env.control_hz)

        def settled() -> bool:  # the hardware reached the last guarded action
            arm = mirror.latest_measured()[left][:7]
            sent = [d["commands_sent"] for d in mirror.summary().values()]
            return np.allclose(arm, twin.action[left][:7], atol=0.02) and min(sent) >= 10

        wait_until(settled, "the rig followed the twin")
        measured = mirror.latest_measured()
        mirror.close()
        summary = mirror.summary()
        assert set(summary) == {"left_arm", "left_hand", "right_arm", "right_hand", "body"}
        assert all(d["errors"] == 0 and d["commands_sent"] >= 10 for d in summary.values())
        assert refused > 0, "the arm never reached the chest: the test did not test the guard"
        # The hardware followed the guarded twin, not the command into the chest.
        np.testing.assert_allclose(measured[left][:7], twin.action[left][:7], atol=0.02)
        body = env.joints.body
        np.testing.assert_allclose(measured[body], env.joints.home[body], atol=HALF_COUNT)
    finally:
        rig.close()
        env.close()
    # Every goal the left arm's servos received: the roll never went past the guarded action.
    lowest = min(goals["22"] for _, goals in rig.received["left_arm"])  # JSON: string keys
    assert lowest >= twin.action[roll] - 1e-3 - 2 * HALF_COUNT
    assert len(rig.received["body"]) >= 10
