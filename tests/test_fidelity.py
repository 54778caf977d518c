"""Our MJCF against the reference models: same kinematics, masses and inertias.

For 200 random joint configurations per embodiment, the flange and the four fingertip-pad
points of our model must match the reference xArm7 + LEAP models within 1 mm. The reference
hand is placed on the reference arm with our documented mount transform, and the pad points
are taken at our pad offsets in the reference fingertip frames, so the check covers every
joint origin, axis and sign along both chains.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.robots import EMBODIMENTS, make_embodiment

# our body -> reference body (Menagerie LEAP names)
REF_DISTAL = {"thumb_distal": "thumb_fingertip", "index_distal": "fingertip",
              "middle_distal": "fingertip_2", "ring_distal": "fingertip_3"}
N_CONFIGS = 200
TOLERANCE_M = 1e-3


def _reference_hand(reference_dir, side: str) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_file(str(reference_dir / "menagerie_leap_hand" / f"{side}_hand.xml"))
    # The reference palm meshes are missing (see reference/README.md); drop all mesh geoms.
    for geom in list(spec.geoms):
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    for light in list(spec.lights):
        spec.delete(light)
    return spec


def _relative_pose(model, data, site_name, body_name):
    """Pose of body ``body_name`` in the frame of site ``site_name``: (pos, quat)."""
    R_site = data.site(site_name).xmat.reshape(3, 3)
    R_body = data.body(body_name).xmat.reshape(3, 3)
    pos = R_site.T @ (data.body(body_name).xpos - data.site(site_name).xpos)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (R_site.T @ R_body).flatten())
    return pos, quat


def _build_pair(reference_dir, embodiment_name):
    embodiment = make_embodiment(embodiment_name)
    ours = build_scene_spec(embodiment, 480, 640).compile()
    ours_data = mujoco.MjData(ours)
    mujoco.mj_kinematics(ours, ours_data)

    ref_spec = mujoco.MjSpec()
    for eff_spec, eff in zip(embodiment.spec.effectors, embodiment.effectors, strict=True):
        arm = mujoco.MjSpec.from_file(str(reference_dir / "menagerie_ufactory_xarm7" / "xarm7_nohand.xml"))
        arm.delete(arm.key("home"))
        base = ref_spec.worldbody.add_frame(pos=list(eff_spec.base_pos))
        # Our link_base frame is the Menagerie link_base frame; Menagerie lifts it 0.12 m.
        arm.body("link_base").pos = [0, 0, 0]
        ref_spec.attach(arm, prefix=eff_spec.prefix, frame=base)
        hand = _reference_hand(reference_dir, eff.side)
        pos, quat = _relative_pose(ours, ours_data, eff.ee_site, eff_spec.prefix + "palm")
        hand.body("palm_lower").pos = list(pos)
        hand.body("palm_lower").quat = list(quat)
        ref_spec.attach(hand, prefix=eff_spec.prefix, site=ref_spec.site(eff_spec.prefix + "attachment_site"))
    return embodiment, ours, ref_spec.compile()


def _ref_joint(name: str) -> str:
    prefix, _, local = name.rpartition("/")
    return f"{prefix}/{local.removeprefix('leap_')}"


@pytest.mark.parametrize("embodiment_name", sorted(EMBODIMENTS))
def test_flange_and_fingertips_match_reference(reference_dir, embodiment_name):
    embodiment, ours, ref = _build_pair(reference_dir, embodiment_name)
    d_ours, d_ref = mujoco.MjData(ours), mujoco.MjData(ref)
    rng = np.random.default_rng(0)
    names = embodiment.joint_names
    lo = np.array([max(ours.joint(n).range[0], -np.pi) for n in names])
    hi = np.array([min(ours.joint(n).range[1], np.pi) for n in names])
    worst = 0.0
    for _ in range(N_CONFIGS):
        q = rng.uniform(lo, hi)
        for n, v in zip(names, q, strict=True):
            d_ours.qpos[ours.joint(n).qposadr[0]] = v
            d_ref.qpos[ref.joint(_ref_joint(n)).qposadr[0]] = v
        mujoco.mj_kinematics(ours, d_ours)
        mujoco.mj_kinematics(ref, d_ref)
        for eff in embodiment.effectors:
            p = eff.name + "/"
            worst = max(worst, np.linalg.norm(d_ours.site(eff.ee_site).xpos - d_ref.site(p + "attachment_site").xpos))
            for site in eff.fingertip_sites:
                body = ours.body(ours.site(site).bodyid[0]).name.removeprefix(p)
                ref_body = d_ref.body(p + REF_DISTAL[body])
                expected = ref_body.xpos + ref_body.xmat.reshape(3, 3) @ ours.site(site).pos
                worst = max(worst, np.linalg.norm(d_ours.site(site).xpos - expected))
    assert worst < TOLERANCE_M, f"worst flange/fingertip error {worst * 1000:.3f} mm"


@pytest.mark.parametrize("embodiment_name", ["xarm7_leap_right", "xarm7_leap_left"])
def test_joint_axes_ranges_masses_inertias_match_reference(reference_dir, embodiment_name):
    embodiment, ours, ref = _build_pair(reference_dir, embodiment_name)
    for name in embodiment.joint_names:
        j_ours, j_ref = ours.joint(name), ref.joint(_ref_joint(name))
        np.testing.assert_allclose(j_ours.range, j_ref.range, atol=1e-6, err_msg=name)
        # Axes in the world at the zero pose (frames differ only by our fixed mount).
        d_o, d_r = mujoco.MjData(ours), mujoco.MjData(ref)
        mujoco.mj_kinematics(ours, d_o)
        mujoco.mj_kinematics(ref, d_r)
        np.testing.assert_allclose(d_o.xaxis[j_ours.id], d_r.xaxis[j_ref.id], atol=1e-5, err_msg=name)
        b_ours, b_ref = ours.body(j_ours.bodyid[0]), ref.body(j_ref.bodyid[0])
        np.testing.assert_allclose(b_ours.mass, b_ref.mass, rtol=1e-4, err_msg=name)
        np.testing.assert_allclose(np.sort(b_ours.inertia), np.sort(b_ref.inertia), rtol=1e-3, err_msg=name)
        np.testing.assert_allclose(b_ours.ipos, b_ref.ipos, atol=1e-5, err_msg=name)
