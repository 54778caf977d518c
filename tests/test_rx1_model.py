"""Our RX-1 MJCF against the RX-1 URDF (``leap_rx1.urdf``, loaded without meshes).

For 200 random configurations of all 52 joints (both arms, both LEAP hands, torso and head),
every joint anchor, the palm frame's centre site and the four fingertip-pad sites of our model
must match the URDF within 1 mm. Pad sites are compared at our pad offsets in the URDF's
fingertip link frames, so the check covers every joint origin, axis and sign along each chain.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.reference import RX1_URDF_LINK, build_rx1_reference_model, rx1_urdf_joint_name
from beavr_sim.robots import make_embodiment

N_CONFIGS = 200
TOLERANCE_M = 1e-3


@pytest.fixture(scope="module")
def rx1():
    embodiment = make_embodiment("rx1")
    return embodiment, build_scene_spec(embodiment, 64, 64).compile()


def test_joints_and_hand_sites_match_urdf(reference_dir, rx1):
    embodiment, ours = rx1
    ref = build_rx1_reference_model(reference_dir, embodiment.spec.body_pos)
    d_ours, d_ref = mujoco.MjData(ours), mujoco.MjData(ref)
    names = embodiment.joint_names
    assert len(names) == 2 * (7 + 16) + 6
    ref_names = [rx1_urdf_joint_name(n) for n in names]
    lo = np.array([ours.joint(n).range[0] for n in names])
    hi = np.array([ours.joint(n).range[1] for n in names])
    rng = np.random.default_rng(0)
    worst, worst_what = 0.0, ""
    for _ in range(N_CONFIGS):
        q = rng.uniform(lo, hi)
        for n, r, v in zip(names, ref_names, q, strict=True):
            d_ours.qpos[ours.joint(n).qposadr[0]] = v
            d_ref.qpos[ref.joint(r).qposadr[0]] = v
        mujoco.mj_kinematics(ours, d_ours)
        mujoco.mj_kinematics(ref, d_ref)
        errors = {
            n: np.linalg.norm(d_ours.joint(n).xanchor - d_ref.joint(r).xanchor)
            for n, r in zip(names, ref_names, strict=True)
        }
        for eff in embodiment.effectors:
            for site in (*eff.fingertip_sites, eff.palm_site):
                body = ours.body(ours.site(site).bodyid[0]).name.removeprefix(eff.name + "/")
                link = d_ref.body(RX1_URDF_LINK[body].format(side=eff.side))
                expected = link.xpos + link.xmat.reshape(3, 3) @ ours.site(site).pos
                errors[site] = np.linalg.norm(d_ours.site(site).xpos - expected)
        what = max(errors, key=errors.get)
        if errors[what] > worst:
            worst, worst_what = errors[what], what
    assert worst < TOLERANCE_M, f"worst error {worst * 1000:.3f} mm at {worst_what}"


def test_joint_axes_and_ranges_match_urdf(reference_dir, rx1):
    """Axes of every joint; ranges of the arm and body joints. The hands are our LEAP model,
    whose ranges test_fidelity checks against Menagerie's LEAP hands; ``leap_rx1.urdf`` gives
    the left thumb's joints 12 and 13 each other's ranges (the only difference)."""
    embodiment, ours = rx1
    ref = build_rx1_reference_model(reference_dir, embodiment.spec.body_pos)
    d_ours, d_ref = mujoco.MjData(ours), mujoco.MjData(ref)
    mujoco.mj_kinematics(ours, d_ours)
    mujoco.mj_kinematics(ref, d_ref)
    for name in embodiment.joint_names:
        j_ours, j_ref = ours.joint(name), ref.joint(rx1_urdf_joint_name(name))
        if "/leap_" not in name:
            np.testing.assert_allclose(j_ours.range, j_ref.range, atol=1e-5, err_msg=name)
        np.testing.assert_allclose(
            d_ours.xaxis[j_ours.id], d_ref.xaxis[j_ref.id], atol=1e-5, err_msg=name
        )


def test_effector_base_pos_is_the_shoulder_site(rx1):
    """``EffectorSpec.base_pos`` (what tasks and experts read) is where the arm is attached."""
    embodiment, ours = rx1
    data = mujoco.MjData(ours)
    data.qpos[embodiment.bind(ours).qpos_adr] = embodiment.home()
    mujoco.mj_kinematics(ours, data)
    for spec in embodiment.spec.effectors:
        np.testing.assert_allclose(
            data.body(spec.prefix + spec.arm.root_body).xpos, spec.base_pos, atol=1e-9
        )


def test_body_joints_come_after_the_effectors_and_hold_home(rx1):
    embodiment, ours = rx1
    joints = embodiment.bind(ours)
    assert joints.names[joints.body] == tuple("body/" + j for j in embodiment.spec.body.joints)
    assert joints.body.stop == joints.size
    assert [sl.stop - sl.start for sl in joints.slices.values()] == [23, 23]
    np.testing.assert_allclose(joints.home[joints.body], embodiment.spec.body.home)


def test_home_pose_is_collision_free(rx1):
    embodiment, ours = rx1
    data = mujoco.MjData(ours)
    data.qpos[embodiment.bind(ours).qpos_adr] = embodiment.home()
    mujoco.mj_forward(ours, data)
    touching = [
        (ours.geom(c.geom1).name, ours.geom(c.geom2).name)
        for c in data.contact[: data.ncon]
        if c.dist < 0
    ]
    assert not touching


def test_head_camera_sees_the_table_and_goes_to_the_headset():
    import gymnasium as gym

    import beavr_sim.envs  # noqa: F401
    from beavr_sim.teleop.session import headset_camera

    env = gym.make(
        "beavr_sim/PickPlace-v0", embodiment="rx1", cameras=["head"], camera_height=48,
        camera_width=64,
    ).unwrapped  # fmt: skip
    try:
        obs, _ = env.reset(seed=0)
        head = obs["pixels"]["head"]
        assert head.shape == (48, 64, 3) and head.std() > 5
        assert not np.array_equal(head, env.render_camera("front"))
        assert headset_camera(env.embodiment) == "head"
        assert headset_camera(make_embodiment("xarm7_leap_right")) == "front"
        # The head looks down at the table: its optical axis points forward and down.
        data = env.data
        R = data.cam("head").xmat.reshape(3, 3)
        look = -R[:, 2]
        assert look[0] > 0.5 and look[2] < -0.3
    finally:
        env.close()
