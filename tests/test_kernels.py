"""The operator's compiled kernels against the numpy / MuJoCo forms they replace.

Point Jacobians and collision rows are checked against ``mj_jac`` and finite differences in
``test_jacobians.py`` and ``test_collision.py``; the pose filter against LERP/SLERP and the
palm frame in ``test_operator.py``. Here: the QP assembly, rotations and the small helpers.
"""

import mujoco
import numpy as np
import pytest

from beavr_sim.operator import kernels
from beavr_sim.operator.filters import so3_exp, so3_log
from beavr_sim.operator.jacobians import PointJacobians
from beavr_sim.operator.retarget import LeapRetargeter, human_template


def _random_rotation(rng):
    return so3_exp(rng.normal(size=3) * rng.uniform(0, np.pi) / np.sqrt(3))


def test_rotation_vector_matches_mujoco_on_every_branch():
    rng = np.random.default_rng(0)
    rotations = [_random_rotation(rng) for _ in range(200)]
    # Each branch of Shepperd's method: trace largest, then x, y, z largest (near pi).
    rotations += [np.eye(3)] + [so3_exp(np.pi * 0.999 * np.eye(3)[a]) for a in range(3)]
    rotations += [so3_exp(1e-9 * rng.normal(size=3))]
    for R in rotations:
        np.testing.assert_allclose(kernels.rotation_vector(R), so3_log(R), atol=1e-9)
        w, x, y, z = kernels.quat_from_matrix(R)
        assert w >= 0 and np.isclose(w * w + x * x + y * y + z * z, 1.0)


def test_arm_qp_is_the_documented_problem():
    rng = np.random.default_rng(1)
    nv, dofs = 12, np.array([0, 1, 2, 3, 4, 5, 6])
    jac = rng.normal(size=(6, nv))
    weights = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _random_rotation(rng), rng.normal(size=3)
    p_hand, R_hand = rng.normal(size=3), _random_rotation(rng)
    qpos, qpos_adr = rng.normal(size=nv), np.array([5, 4, 3, 2, 1, 0, 6])
    posture, lower_q, upper_q = rng.normal(size=7), -np.ones(7), np.ones(7)
    qpos[qpos_adr[0]] = 1.5  # past its upper limit: may only move back
    # Outputs start as garbage: the kernel must overwrite every entry.
    H, c, lower, upper = np.full((7, 7), 9.0), np.full(7, 9.0), np.full(7, 9.0), np.full(7, 9.0)
    kernels.arm_qp(
        jac, dofs, weights, T, p_hand, R_hand, qpos, qpos_adr,
        posture, 1e-4, 1e-4, 1e-3, 0.07, lower_q, upper_q, 0.95, H, c, lower, upper,
    )  # fmt: skip
    e = weights * np.concatenate([T[:3, 3] - p_hand, so3_log(T[:3, :3] @ R_hand.T)])
    J = weights[:, None] * jac[:, dofs]
    q = qpos[qpos_adr]
    np.testing.assert_allclose(H, J.T @ J + (1e-4 + 1e-4 + 1e-3 * e @ e) * np.eye(7), atol=1e-12)
    np.testing.assert_allclose(c, -(e @ J) + 1e-4 * (q - posture), atol=1e-12)
    np.testing.assert_allclose(upper, np.maximum(np.minimum(0.95 * (upper_q - q), 0.07), 0))
    np.testing.assert_allclose(lower, np.minimum(np.maximum(0.95 * (lower_q - q), -0.07), 0))
    assert upper[0] == 0.0 and lower[0] < 0.0


def test_points_qp_is_the_weighted_least_squares_step():
    retargeter = LeapRetargeter("right")
    data, model = retargeter.configuration.data, retargeter.model
    rng = np.random.default_rng(2)
    retargeter.configuration.update(rng.uniform(model.jnt_range[:, 0], model.jnt_range[:, 1]))
    points = retargeter.points
    positions = points._update_positions(data).copy()
    targets = positions + 0.01 * rng.normal(size=positions.shape)
    cost = points.base_cost * rng.uniform(0.5, 2.0, size=points.base_cost.size)
    cost[:3] = 0.0  # a held finger's point
    held = np.zeros(model.nv, dtype=bool)
    held[[1, 5]] = True
    posture = rng.normal(size=model.nv)
    jac = PointJacobians(model)
    nv = model.nv
    H, c = np.full((nv, nv), 9.0), np.full(nv, 9.0)
    lower, upper = np.full(nv, 9.0), np.full(nv, 9.0)
    kernels.points_qp(
        data.cdof, data.subtree_com, jac.root, jac.chain, points._bodies, positions,
        targets, cost, data.qpos, posture, 1e-4, 2e-4, retargeter._lower_qpos,
        retargeter._upper_qpos, 0.95, 0.1, held, H, c, lower, upper,
    )  # fmt: skip
    J = np.concatenate(
        [_mj_jac(model, data, b, p) for b, p in zip(points._bodies, positions, strict=True)]
    )
    WJ = cost[:, None] * J
    error = (positions - targets).ravel()
    np.testing.assert_allclose(H, WJ.T @ WJ + 2e-4 * np.eye(model.nv), atol=1e-12)
    np.testing.assert_allclose(c, (cost * error) @ WJ + 1e-4 * (data.qpos - posture), atol=1e-12)
    q = data.qpos
    expected_upper = np.minimum(0.95 * (retargeter._upper_qpos - q), 0.1)
    expected_lower = np.maximum(0.95 * (retargeter._lower_qpos - q), -0.1)
    expected_upper[held] = expected_lower[held] = 0.0
    np.testing.assert_allclose(upper, expected_upper)
    np.testing.assert_allclose(lower, expected_lower)


def _mj_jac(model, data, body, point):
    jacp = np.zeros((3, model.nv))
    mujoco.mj_jac(model, data, jacp, None, point, int(body))
    return jacp


def test_select_contacts_keeps_each_pairs_closest_in_pair_order():
    rng = np.random.default_rng(3)
    lookup = np.full((6, 6), -1, dtype=np.int64)
    pairs = [(0, 3), (1, 4), (2, 5), (0, 5)]
    for i, (a, b) in enumerate(pairs):
        lookup[a, b] = lookup[b, a] = i
    which = rng.integers(0, 3, size=12)  # pair 3 never reports
    dist = rng.uniform(-0.01, 0.03, size=12)
    which[5], dist[5] = which[2], dist[2]  # a tie: the first of the two counts
    dist[2] = dist[5] = dist[which == which[2]].min()
    geom = np.array([pairs[i] for i in which], dtype=np.int32)
    keep, pair = kernels.select_contacts(geom, dist, lookup, len(pairs), True)
    # The numpy form: sort by (pair, distance), keep the first of each pair (stable).
    order = np.lexsort((dist, which))
    first = np.r_[True, which[order][1:] != which[order][:-1]]
    np.testing.assert_array_equal(keep, order[first])
    np.testing.assert_array_equal(pair, which[order[first]])
    keep_all, pair_all = kernels.select_contacts(geom, dist, lookup, len(pairs), False)
    np.testing.assert_array_equal(keep_all, np.arange(12))
    np.testing.assert_array_equal(pair_all, which)


def test_point_targets_map_tracked_points_and_reject_nan_untouched():
    rng = np.random.default_rng(4)
    keypoints = rng.normal(size=(26, 3))
    human_ids = np.array([3, 7, 11], dtype=np.int64)
    scales = np.array([1.7, 1.8, 1.8])
    offset = np.array([0.01, -0.02, 0.03])
    targets, cost, base_cost = np.zeros((3, 3)), np.zeros(9), np.arange(9.0)
    tracked = np.ones(26, dtype=bool)
    assert (
        kernels.point_targets(
            keypoints, tracked, human_ids, scales, offset, targets, cost, base_cost
        )
        == 1
    )
    np.testing.assert_allclose(targets, offset + scales[:, None] * keypoints[human_ids])
    np.testing.assert_array_equal(cost, base_cost)
    tracked[7] = False
    before = targets.copy()
    keypoints[3] += 1.0
    assert (
        kernels.point_targets(
            keypoints, tracked, human_ids, scales, offset, targets, cost, base_cost
        )
        == 0
    )
    np.testing.assert_allclose(targets[0], offset + 1.7 * keypoints[3])
    np.testing.assert_array_equal(targets[1], before[1])  # untracked: kept
    keypoints[11, 2] = np.nan
    before = targets.copy()
    assert (
        kernels.point_targets(
            keypoints, tracked, human_ids, scales, offset, targets, cost, base_cost
        )
        == -1
    )
    np.testing.assert_array_equal(targets, before)
    keypoints[11, 2] = np.inf
    tracked[11] = False  # NaN/inf in an untracked point is ignored
    assert (
        kernels.point_targets(
            keypoints, tracked, human_ids, scales, offset, targets, cost, base_cost
        )
        == 0
    )


def test_small_helpers_match_numpy():
    rng = np.random.default_rng(5)
    values, index = rng.normal(size=10), np.array([7, 2, 2, 9])
    lower, upper = -0.5 * np.ones(4), 0.5 * np.ones(4)
    clipped = np.full(4, 9.0)
    kernels.gather_clip(values, index, lower, upper, clipped)
    np.testing.assert_array_equal(clipped, np.clip(values[index], -0.5, 0.5))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _random_rotation(rng), rng.normal(size=3)
    points, in_palm = rng.normal(size=(26, 3)), np.full((26, 3), 9.0)
    kernels.in_frame(points, T, in_palm)
    np.testing.assert_allclose(in_palm, (points - T[:3, 3]) @ T[:3, :3], atol=1e-12)
    lower_b, upper_b, h = -np.ones(3), np.ones(3), np.array([0.5, 0.2])
    bupper, blower, sense = np.full(6, 9.0), np.full(6, 9.0), np.full(6, 7, dtype=np.int32)
    assert kernels.stack_bounds(lower_b, upper_b, h, bupper, blower, sense) == 5
    np.testing.assert_array_equal(bupper[:5], [1, 1, 1, 0.5, 0.2])
    np.testing.assert_array_equal(blower[:5], [-1, -1, -1, -1e30, -1e30])
    assert not sense[:5].any() and sense[5] == 7  # only the first m entries are written
    # Too short: nothing written, -1.
    assert kernels.stack_bounds(lower_b, upper_b, h, bupper[:4], blower, sense) == -1
    assert bupper[0] == 1 and sense[5] == 7


@pytest.mark.parametrize("bad", ["nan", "inf"])
def test_retarget_rejects_non_finite_tracked_tips_without_moving(bad):
    retargeter = LeapRetargeter("left")
    keypoints = human_template("left")
    q_before = retargeter.q
    keypoints[retargeter._human_ids[0], 0] = float(bad)
    with pytest.raises(ValueError, match="NaN/inf"):
        retargeter.retarget(keypoints)
    np.testing.assert_array_equal(retargeter.q, q_before)
