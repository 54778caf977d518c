"""The fast collision limit gives exactly mink's constraint rows (hand and arm models)."""

from __future__ import annotations

import mink
import mujoco
import numpy as np
import pytest

from beavr_sim.robots import make_embodiment
from beavr_sim.teleop.arm_ik import ArmIK, ArmIKConfig
from beavr_sim.teleop.collision import CollisionLimit
from beavr_sim.teleop.retarget import LeapRetargeter, finger_geoms


def _compare(limit, configuration, q_samples):
    active = 0
    for q in q_samples:
        configuration.update(q)
        fast = limit.compute_qp_inequalities(configuration, 1 / 30)
        limit.broadphase = False  # mink's own computation, every pair
        slow = mink.CollisionAvoidanceLimit.compute_qp_inequalities(limit, configuration, 1 / 30)
        limit.broadphase = True
        finite = np.isfinite(slow.h)
        np.testing.assert_array_equal(np.isfinite(fast.h), finite)
        np.testing.assert_allclose(fast.h[finite], slow.h[finite], atol=1e-12)
        np.testing.assert_allclose(fast.G, slow.G, atol=1e-12)
        active += int(finite.sum())
    assert active > 0, "no pair came within the detection distance: the test proves nothing"


def _hand_samples(r, n=100, seed=1):
    rng = np.random.default_rng(seed)
    lo, hi = r.map.range[:, 0], r.map.range[:, 1]
    samples = []
    for _ in range(n):
        q = r.configuration.q.copy()
        q[r.map.qpos_adr] = rng.uniform(lo, hi)
        samples.append(q)
    return samples


def test_finger_limit_matches_mink():
    r = LeapRetargeter("right")
    geoms = finger_geoms(r.model)
    fingers = list(geoms)
    pairs = [(geoms[a], geoms[b]) for i, a in enumerate(fingers) for b in fingers[i + 1 :]]
    limit = CollisionLimit(
        r.model, pairs, collision_detection_distance=0.03, minimum_distance_from_collisions=0.003
    )
    _compare(limit, r.configuration, _hand_samples(r))


def test_per_pair_detection_distance_only_drops_far_finger_pairs():
    """The retargeter's limit: thumb pairs watched from 3 cm, finger-finger pairs from 1.5 cm."""
    r = LeapRetargeter("right")
    limit = r.collision_limit
    thumb = set(finger_geoms(r.model)["thumb"])
    kept = dropped = 0
    for q in _hand_samples(r, 50, seed=3):
        r.configuration.update(q)
        active = np.isfinite(limit.compute_qp_inequalities(r.configuration, 1.0).h)
        for idx, (g1, g2) in enumerate(limit.geom_id_pairs):
            dist = mujoco.mj_geomDistance(r.model, r.configuration.data, g1, g2, 1.0, None)
            bound = 0.03 if (g1 in thumb or g2 in thumb) else 0.015
            assert active[idx] == (dist < bound), (g1, g2, dist)
            kept += int(active[idx])
            dropped += int(not active[idx] and dist < 0.03)
    assert kept > 0 and dropped > 0


@pytest.mark.parametrize("side", ["right", "left"])
def test_arm_limit_matches_mink(side):
    emb = make_embodiment(f"xarm7_leap_{side}")
    ik = ArmIK(emb, side, 1 / 30)
    limit = ik.collision
    rng = np.random.default_rng(2)
    home = ik.configuration.q.copy()
    samples = []
    for _ in range(100):
        q = home.copy()
        q[ik.joints.qpos_adr[:7]] += rng.normal(0.0, 0.6, 7)  # reaches down to the table
        samples.append(q)
    _compare(limit, ik.configuration, samples)


def test_arm_ik_stops_the_fingers_above_the_table():
    """A target 10 cm below the table: the IK keeps the fingertips at its margin; without
    collision avoidance they would go into the table (so the check is what stops them)."""
    emb = make_embodiment("xarm7_leap_right")
    reached = {}
    for avoid in (True, False):
        ik = ArmIK(emb, "right", 1 / 30, ArmIKConfig(collision_avoidance=avoid))
        T = ik.T_world_hand()
        T[2, 3] -= 0.15
        for _ in range(120):
            ik.step(T)
        data, table = ik.configuration.data, ik.model.geom("table_top").id
        tips = [
            g
            for g in range(ik.model.ngeom)
            if ik.model.body(ik.model.geom_bodyid[g]).name.endswith("_distal")
        ]
        reached[avoid] = min(
            mujoco.mj_geomDistance(ik.model, data, g, table, 1.0, None) for g in tips
        )
    margin = ArmIKConfig().collision_margin
    assert reached[True] > margin - 5e-4, reached
    assert reached[False] < 0.0, reached
