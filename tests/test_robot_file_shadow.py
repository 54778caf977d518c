"""A robot file whose hand comes from its own model: the Franka Panda with the Shadow hand, both
inside the gymnasium-robotics wheel (``examples/robots/franka_shadow_right.toml``; the wheel is
fetched or skipped as in ``test_robot_file_franka.py``). The file passes ``robots check``; its
hand part carries the model's 22 finger joints with the twin's servos and limits; and the
bundled PickupBox VR trace replays through the full teleop pipeline, the fingers retargeted
from the model, with no guard refusal.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
from fixtures_shared import robotics_wheel_on_path

from beavr_sim.operator.retarget_model import ModelHandRetargeter
from beavr_sim.robots import make_embodiment
from beavr_sim.teleop.session import SessionOptions, build_loop

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "robots"
ROBOT = EXAMPLES / "franka_shadow_right.toml"
#: The other hand on the xArm7 (issue 43's second pairing): our own xArm7 MJCF from a file.
XARM7_ROBOT = EXAMPLES / "xarm7_shadow_right.toml"


@pytest.fixture(scope="module")
def wheel_on_path():
    """gymnasium-robotics importable (not imported) while the module's tests run."""
    with robotics_wheel_on_path():
        yield


@pytest.fixture(scope="module")
def shadow_robot(wheel_on_path):
    """The Franka + Shadow robot file's path."""
    return str(ROBOT)


@pytest.fixture(scope="module", params=[ROBOT, XARM7_ROBOT], ids=["franka", "xarm7"])
def any_shadow_robot(request, wheel_on_path):
    """Each robot file with the Shadow hand."""
    return str(request.param)


def test_the_shadow_hand_becomes_a_part_with_servos_on_its_joints(shadow_robot):
    embodiment = make_embodiment(shadow_robot)
    hand = embodiment.spec.effectors[0].hand
    assert hand.name == "shadow" and len(hand.joints) == 22  # the wrist stays behind
    assert hand.max_velocity == pytest.approx(math.pi)  # the file's 180 deg/s
    scene = mujoco.MjSpec()
    embodiment.attach_to(scene)
    model = scene.compile()
    joints = embodiment.bind(model)
    assert joints.size == 7 + 22
    fingers = joints.actuator_ids[7:]
    np.testing.assert_allclose(model.actuator_gainprm[fingers, 0], 2.0)  # the file's kp
    np.testing.assert_allclose(model.actuator_biasprm[fingers, 2], -0.2)  # kv = kp / 10
    np.testing.assert_allclose(model.actuator_ctrlrange[fingers], model.jnt_range[
        [model.joint(n).id for n in joints.names[7:]]])  # fmt: skip
    assert not model.dof_damping[joints.qvel_adr[7:]].any()  # the servo's kv only
    assert model.ntendon == 0  # the J0/J1 coupling: independent joints
    data = mujoco.MjData(model)
    data.qpos[joints.qpos_adr] = joints.home
    mujoco.mj_kinematics(model, data)
    R = data.body("right/hand").xmat.reshape(3, 3)
    tip = data.site("right/tip_middle").xpos - data.body("right/hand").xpos
    assert (R.T @ tip)[2] > 0.15  # the fingers along the hand frame's +z, as LEAP's


def test_the_shadow_robot_files_pass_the_check(any_shadow_robot, capsys):
    from beavr_sim.robots.__main__ import main

    assert main(["check", any_shadow_robot, "--task", "PickupBox"]) == 0
    out = capsys.readouterr().out
    assert "check_env (PickupBox): passed" in out
    assert "hand shadow: 22 joints; finger scales (human -> hand): thumb " in out
    assert "missing: nothing" in out
    if any_shadow_robot == str(XARM7_ROBOT):
        # The model's own exclude (its base welded to the world touches link1) is kept.
        assert "touching at home: nothing" in out


def test_a_bundled_trace_drives_the_shadow_hand_with_no_guard_refusal(
    any_shadow_robot, monkeypatch
):
    fingers = []  # each retargeted hand command

    def retarget(self, keypoints, tracked=None, dt=None):
        q = original(self, keypoints, tracked, dt)
        fingers.append(q)
        return q

    original = ModelHandRetargeter.retarget
    monkeypatch.setattr(ModelHandRetargeter, "retarget", retarget)
    options = SessionOptions(
        task="PickupBox", source="trace", clock="virtual", viser=False, headless=True,
        progress=False, embodiment=any_shadow_robot,
    )  # fmt: skip
    loop = build_loop(options)
    env = loop.twin.env
    try:
        start = env.data.qpos[env.joints.qpos_adr[7:]].copy()
        summary = loop.run()
        guard = loop.twin.guard
        end = env.data.qpos[env.joints.qpos_adr[7:]].copy()
    finally:
        env.close()
    assert summary.embodiment == Path(any_shadow_robot).stem
    assert summary.commands_applied > 200  # the whole trace reached the twin
    assert guard.checks > 200 and guard.refusals == 0, guard.refusals_by_rule
    assert "guard" not in summary.holds.get("right", {}), summary.holds
    assert guard.max_velocity[7:] == pytest.approx([math.pi] * 22)  # the hand's own cap
    # The fingers followed the operator's hand: retargeted every frame, and the twin's moved.
    assert len(fingers) > 200 and np.ptp(np.array(fingers), axis=0).max() > 0.8
    assert np.abs(end - start).max() > 0.2
