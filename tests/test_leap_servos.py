"""The simulated LEAP hand has the real hand's servo gains and torque cap (docs/models.md, "LEAP
servos"): kp from the LEAP API's position P gain, the cap from the current limit of the chosen
variant (full 550 mA, Lite 350 mA) times the XC330-M288-T's torque constant."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from beavr_sim.assets import mjcf_path
from beavr_sim.envs.beavr_env import BeavrEnv
from beavr_sim.hardware.leap.config import VARIANT_CURRENT_MA, LeapHandConfig
from beavr_sim.hardware.rig import RigConfig
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots.parts import (
    LEAP_HAND,
    LEAP_VARIANT_CURRENT_MA,
    XC330_M288_TORQUE_CONSTANT,
    dynamixel_position_kp,
)

#: The derived numbers (docs/models.md): K_t = 0.93 N m / 1.80 A.
EXPECTED_CAP = {"full": 0.2842, "lite": 0.1808}
EXPECTED_KP = {"finger": 1.5788, "side": 1.1841}
SIDE_JOINTS = ("leap_0", "leap_4", "leap_8")


def _expected_kp(joint: str) -> float:
    """kp (N m/rad) of ``joint`` from the hardware config's P gain for its motor."""
    motor = int(joint.rsplit("_", 1)[1])
    p_gain = LeapHandConfig(port="p").gains(motor)[0]
    return dynamixel_position_kp(p_gain, XC330_M288_TORQUE_CONSTANT)


def test_derived_numbers():
    assert XC330_M288_TORQUE_CONSTANT == pytest.approx(0.5167, abs=1e-4)
    for variant, cap in EXPECTED_CAP.items():
        assert LEAP_HAND.torque_cap(variant) == pytest.approx(cap, abs=1e-4)
    assert _expected_kp("leap_1") == pytest.approx(EXPECTED_KP["finger"], abs=1e-4)
    for joint in SIDE_JOINTS:
        assert _expected_kp(joint) == pytest.approx(EXPECTED_KP["side"], abs=1e-4)
        assert _expected_kp(joint) == pytest.approx(0.75 * _expected_kp("leap_1"))


@pytest.mark.parametrize("side", ["right", "left"])
def test_hand_files_have_the_converted_gains_and_full_cap(side):
    model = mujoco.MjModel.from_xml_path(str(mjcf_path(LEAP_HAND.mjcf(side))))
    cap = LEAP_HAND.torque_cap("full")
    assert model.nu == len(LEAP_HAND.joints)
    for a, joint_name in enumerate(LEAP_HAND.joints):  # actuators in motor-id order
        joint = model.actuator_trnid[a, 0]
        assert model.joint(joint).name == joint_name == model.actuator(a).name
        kp = _expected_kp(joint_name)
        assert model.actuator_gainprm[a, 0] == pytest.approx(kp, rel=1e-3), joint_name
        assert model.actuator_biasprm[a, 1] == pytest.approx(-kp, rel=1e-3), joint_name
        assert model.actuator_biasprm[a, 2] < 0, joint_name  # damped (dampratio 1)
        np.testing.assert_allclose(model.actuator_forcerange[a], [-cap, cap], rtol=1e-3)
        np.testing.assert_allclose(model.jnt_actfrcrange[joint], [-cap, cap], rtol=1e-3)


def _hand_actuators(env: BeavrEnv) -> list[tuple[str, int]]:
    return [
        (name, int(env.joints.actuator_ids[i]))
        for i, name in enumerate(env.joints.names)
        if "/leap_" in name
    ]


@pytest.mark.parametrize("variant", ["full", "lite"])
@pytest.mark.parametrize("embodiment", ["xarm7_leap_bimanual", "rx1"])
def test_compiled_scene_has_the_variants_cap(variant, embodiment):
    env = BeavrEnv(task="Playground", embodiment=embodiment, hand_variant=variant)
    try:
        model = env.model
        cap = EXPECTED_CAP[variant]
        assert env.hand_variant == variant
        hand = _hand_actuators(env)
        assert len(hand) == 16 * len(env.embodiment.effectors)
        for name, a in hand:
            local = name.rsplit("/", 1)[1]
            expected_kp = EXPECTED_KP["side" if local in SIDE_JOINTS else "finger"]
            assert model.actuator_gainprm[a, 0] == pytest.approx(expected_kp, abs=1e-3), name
            np.testing.assert_allclose(model.actuator_forcerange[a], [-cap, cap], atol=1e-4)
            joint = model.actuator_trnid[a, 0]
            np.testing.assert_allclose(model.jnt_actfrcrange[joint], [-cap, cap], atol=1e-4)
        # The arms keep their own limits.
        arm = [
            a for i, a in enumerate(env.joints.actuator_ids) if "/leap_" not in env.joints.names[i]
        ]
        assert all(model.actuator_forcerange[a, 1] > 1.0 for a in arm)
    finally:
        env.close()


def test_unknown_variant_lists_the_valid_ones():
    with pytest.raises(UnknownNameError, match="hand variant") as info:
        BeavrEnv(task="Playground", hand_variant="mini")
    assert "full" in str(info.value) and "lite" in str(info.value)
    with pytest.raises(ValueError, match="full, lite"):
        LEAP_HAND.torque_cap("pro")


def test_hardware_config_and_sim_agree_on_the_current_limit():
    assert VARIANT_CURRENT_MA is LEAP_VARIANT_CURRENT_MA  # one place
    assert set(LEAP_HAND.variants) == set(VARIANT_CURRENT_MA) == {"full", "lite"}
    for variant in LEAP_HAND.variants:
        config = LeapHandConfig(port="p", variant=variant)
        assert config.goal_current_ma == LEAP_HAND.current_limit_ma_by_variant[variant]
        assert LEAP_HAND.torque_cap(variant) == pytest.approx(
            XC330_M288_TORQUE_CONSTANT * config.goal_current_ma / 1000
        )
    # The MJCF's gains are the driver's defaults converted.
    config = LeapHandConfig(port="p")
    assert config.gains(1)[0] == 600 and config.gains(0)[0] == 450


def _run(model, data, seconds: float) -> None:
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)


@pytest.mark.parametrize("variant", ["full", "lite"])
# Index flexion from half-closed, and the index's side-to-side joint pushed away from the
# middle finger (towards it, the fingers touch).
@pytest.mark.parametrize(("joint", "target"), [("leap_1", 0.5), ("leap_0", 0.0)])
def test_finger_holds_below_the_cap_and_gives_way_above(variant, joint, target):
    """An external torque on a finger joint held at a target: below the cap the servo holds it,
    deflected by torque / kp; above the cap the actuator force saturates at the cap and the
    joint gives way."""
    env = BeavrEnv(task="Playground", hand_variant=variant)
    try:
        env.reset(seed=0)
        model, data = env.model, env.data
        model.opt.gravity[:] = 0.0
        i = env.joints.names.index(f"right/{joint}")
        a, qadr, dof = (
            int(env.joints.actuator_ids[i]),
            int(env.joints.qpos_adr[i]),
            int(env.joints.qvel_adr[i]),
        )
        cap, kp = LEAP_HAND.torque_cap(variant), model.actuator_gainprm[a, 0]
        data.ctrl[a] = target
        data.qpos[qadr] = target
        mujoco.mj_forward(model, data)

        data.qfrc_applied[dof] = -0.8 * cap
        _run(model, data, 1.0)
        assert target - data.qpos[qadr] == pytest.approx(0.8 * cap / kp, rel=0.05)
        assert data.actuator_force[a] == pytest.approx(0.8 * cap, rel=0.02)
        assert data.ncon == 0

        data.qfrc_applied[dof] = -1.5 * cap
        _run(model, data, 1.0)
        assert data.actuator_force[a] == pytest.approx(cap, rel=1e-3)
        assert data.qfrc_actuator[dof] == pytest.approx(cap, rel=1e-3)
        assert data.qpos[qadr] < target - cap / kp - 0.2  # gave way
        assert data.ncon == 0  # nothing but the servo held the finger
    finally:
        env.close()


def _rig(tmp_path, *variants: str) -> str:
    text = ""
    for side, variant in zip(("right", "left"), variants, strict=False):
        text += (
            f'[[devices]]\nname = "{side}_hand"\nkind = "leap"\neffector = "{side}"\n'
            f'port = "/dev/ttyUSB{len(text)}"\nvariant = "{variant}"\n\n'
        )
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return str(path)


def test_rig_leap_variant(tmp_path):
    assert RigConfig.from_toml(_rig(tmp_path, "lite")).leap_variant() == "lite"
    assert RigConfig.from_toml(_rig(tmp_path, "full", "full")).leap_variant() == "full"
    with pytest.raises(ValueError, match="right_hand 'full', left_hand 'lite'"):
        RigConfig.from_toml(_rig(tmp_path, "full", "lite")).leap_variant()


def test_session_takes_the_variant_from_the_rig_or_the_flag(tmp_path):
    from beavr_sim.teleop.__main__ import build_parser
    from beavr_sim.teleop.session import SessionOptions

    def options(*argv: str) -> SessionOptions:
        args = build_parser().parse_args(["--task", "pour", "--source", "trace", *argv])
        return SessionOptions.from_args(args)

    assert options().leap_variant == "full"
    assert options("--leap-variant", "lite").leap_variant == "lite"
    rig = _rig(tmp_path, "lite")
    mirrored = ("--mirror-hardware", "--hardware-config", rig)
    assert options(*mirrored).leap_variant == "lite"
    assert options(*mirrored, "--leap-variant", "lite").leap_variant == "lite"
    with pytest.raises(ValueError, match="leave out --leap-variant"):
        options(*mirrored, "--leap-variant", "full")
    with pytest.raises(SystemExit):
        options("--leap-variant", "mini")


def test_mirror_refuses_a_twin_of_another_variant(tmp_path):
    from beavr_sim.teleop.mirroring import RigChoice, connect_mirror

    env = BeavrEnv(task="Playground")  # full
    try:
        with pytest.raises(ValueError, match="'lite' but the twin's are 'full'"):
            connect_mirror(RigChoice(str(_rig(tmp_path, "lite"))), env, [])
    finally:
        env.close()
