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
from beavr_sim.reference import REFERENCE_DISTAL_BODY, build_reference_model, reference_joint_name
from beavr_sim.robots import EMBODIMENTS, make_embodiment

N_CONFIGS = 200
TOLERANCE_M = 1e-3


def _build_pair(reference_dir, embodiment_name):
    embodiment = make_embodiment(embodiment_name)
    ours = build_scene_spec(embodiment, 480, 640).compile()
    return embodiment, ours, build_reference_model(embodiment, ours, reference_dir)


XARM_EMBODIMENTS = sorted(n for n, e in EMBODIMENTS.items() if e.body is None)


@pytest.mark.parametrize("embodiment_name", XARM_EMBODIMENTS)
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
            d_ref.qpos[ref.joint(reference_joint_name(n)).qposadr[0]] = v
        mujoco.mj_kinematics(ours, d_ours)
        mujoco.mj_kinematics(ref, d_ref)
        for eff in embodiment.effectors:
            p = eff.name + "/"
            worst = max(
                worst,
                np.linalg.norm(
                    d_ours.site(eff.ee_site).xpos - d_ref.site(p + "attachment_site").xpos
                ),
            )
            for site in eff.fingertip_sites:
                body = ours.body(ours.site(site).bodyid[0]).name.removeprefix(p)
                ref_body = d_ref.body(p + REFERENCE_DISTAL_BODY[body])
                expected = ref_body.xpos + ref_body.xmat.reshape(3, 3) @ ours.site(site).pos
                worst = max(worst, np.linalg.norm(d_ours.site(site).xpos - expected))
    assert worst < TOLERANCE_M, f"worst flange/fingertip error {worst * 1000:.3f} mm"


@pytest.mark.parametrize("embodiment_name", ["xarm7_leap_right", "xarm7_leap_left"])
def test_joint_axes_ranges_masses_inertias_match_reference(reference_dir, embodiment_name):
    embodiment, ours, ref = _build_pair(reference_dir, embodiment_name)
    for name in embodiment.joint_names:
        j_ours, j_ref = ours.joint(name), ref.joint(reference_joint_name(name))
        np.testing.assert_allclose(j_ours.range, j_ref.range, atol=1e-6, err_msg=name)
        # Axes in the world at the zero pose (frames differ only by our fixed mount).
        d_o, d_r = mujoco.MjData(ours), mujoco.MjData(ref)
        mujoco.mj_kinematics(ours, d_o)
        mujoco.mj_kinematics(ref, d_r)
        np.testing.assert_allclose(
            d_o.xaxis[j_ours.id], d_r.xaxis[j_ref.id], atol=1e-5, err_msg=name
        )
        b_ours, b_ref = ours.body(j_ours.bodyid[0]), ref.body(j_ref.bodyid[0])
        np.testing.assert_allclose(b_ours.mass, b_ref.mass, rtol=1e-4, err_msg=name)
        np.testing.assert_allclose(
            np.sort(b_ours.inertia), np.sort(b_ref.inertia), rtol=1e-3, err_msg=name
        )
        np.testing.assert_allclose(b_ours.ipos, b_ref.ipos, atol=1e-5, err_msg=name)
