"""Batched point Jacobians agree with MuJoCo's mj_jac and with finite differences."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from beavr_sim.assets import mjcf_path
from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.operator.jacobians import PointJacobians
from beavr_sim.robots import LEAP_HAND, make_embodiment


def _models():
    leap = mujoco.MjModel.from_xml_path(str(mjcf_path(LEAP_HAND.mjcf("right"))))
    arm = build_scene_spec(make_embodiment("xarm7_leap_bimanual"), 64, 64).compile()
    return {"leap": leap, "bimanual": arm}


@pytest.fixture(scope="module", params=["leap", "bimanual"])
def model(request):
    return _models()[request.param]


def _random_state(model, rng):
    data = mujoco.MjData(model)
    lo, hi = model.jnt_range[:, 0], model.jnt_range[:, 1]
    for j in range(model.njnt):
        if model.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            a = model.jnt_qposadr[j]
            data.qpos[a] = rng.uniform(lo[j], hi[j]) if model.jnt_limited[j] else rng.normal()
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    return data


def test_point_jacobians_match_mj_jac(model):
    rng = np.random.default_rng(0)
    jac = PointJacobians(model)
    for _ in range(5):
        data = _random_state(model, rng)
        bodies = rng.integers(0, model.nbody, size=12)
        points = data.xpos[bodies] + rng.normal(scale=0.05, size=(12, 3))
        J = jac.points(data, bodies, points)
        for i, (b, p) in enumerate(zip(bodies, points, strict=True)):
            ref = np.zeros((3, model.nv))
            mujoco.mj_jac(model, data, ref, None, p, int(b))
            np.testing.assert_allclose(J[i], ref, atol=1e-12)


def test_normal_rows_are_the_derivative_of_the_separation(model):
    """n . (p1 - p2) with both points body-fixed: its derivative by finite differences."""
    rng = np.random.default_rng(1)
    jac = PointJacobians(model)
    data = _random_state(model, rng)
    moving = [b for b in range(1, model.nbody) if jac.chain[b].any()]
    b1, b2 = rng.choice(moving, size=6), rng.choice(moving, size=6)
    p1 = data.xpos[b1] + rng.normal(scale=0.03, size=(6, 3))
    p2 = data.xpos[b2] + rng.normal(scale=0.03, size=(6, 3))
    n = rng.normal(size=(6, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rows = jac.normal_rows(data, n, b1, p1, b2, p2)
    # Body-fixed coordinates of the points, to move them with the bodies.
    local1 = np.einsum("kji,kj->ki", data.xmat[b1].reshape(-1, 3, 3), p1 - data.xpos[b1])
    local2 = np.einsum("kji,kj->ki", data.xmat[b2].reshape(-1, 3, 3), p2 - data.xpos[b2])

    def separation(qpos):
        d = mujoco.MjData(model)
        d.qpos[:] = qpos
        mujoco.mj_kinematics(model, d)
        w1 = d.xpos[b1] + np.einsum("kij,kj->ki", d.xmat[b1].reshape(-1, 3, 3), local1)
        w2 = d.xpos[b2] + np.einsum("kij,kj->ki", d.xmat[b2].reshape(-1, 3, 3), local2)
        return np.einsum("ki,ki->k", n, w1 - w2)

    assert model.nq == model.nv  # hinge / slide joints only: qpos and qvel align
    eps = 1e-6
    fd = np.zeros_like(rows)
    for k in range(model.nv):
        dq = np.zeros(model.nq)
        dq[k] = eps
        fd[:, k] = (separation(data.qpos + dq) - separation(data.qpos - dq)) / (2 * eps)
    np.testing.assert_allclose(rows, fd, atol=1e-6)
