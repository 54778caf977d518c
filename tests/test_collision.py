"""The collision limit: mink's constraint rows (hand and arm models), distances from one
``mj_collision`` that agree with ``mj_geomDistance``, and rows that are the derivative of
the distance (finite differences)."""

from __future__ import annotations

import mink
import mujoco
import numpy as np
import pytest

from beavr_sim.assets import mjcf_path
from beavr_sim.operator.arm_ik import ArmIK, ArmIKConfig
from beavr_sim.operator.collision import CollisionLimit
from beavr_sim.operator.obstacles import fixture_obstacles
from beavr_sim.operator.retarget import LeapRetargeter, finger_geoms
from beavr_sim.robots import make_embodiment
from beavr_sim.robots.parts import LEAP_HAND


def _compare(limit, configuration, q_samples):
    """Our rows against mink's own computation (``mj_geomDistance`` per pair): the same
    pairs active, and for separated pairs the same bound and row, up to the convex
    solvers' tolerance (box-box pairs run on mesh twins: rare 1 mm outliers)."""
    dt = 1 / 30
    dist_errors, row_errors = [], []
    for q in q_samples:
        configuration.update(q)
        fast = limit.compute_qp_inequalities(configuration, dt)
        slow = mink.CollisionAvoidanceLimit.compute_qp_inequalities(limit, configuration, dt)
        finite = np.isfinite(slow.h)
        for i in np.flatnonzero(np.isfinite(fast.h) != finite):
            g1, g2 = limit.geom_id_pairs[i]
            dist = mujoco.mj_geomDistance(limit.model, configuration.data, g1, g2, 1.0, None)
            # Only at the detection boundary may the two solvers disagree on a pair.
            assert abs(dist - limit._distmax[i]) < 1e-3, (g1, g2, dist)
        for i in np.flatnonzero(finite & np.isfinite(fast.h)):
            g1, g2 = limit.geom_id_pairs[i]
            dist = mujoco.mj_geomDistance(limit.model, configuration.data, g1, g2, 1.0, None)
            if dist <= limit.minimum_distance_from_collisions:
                continue  # in contact: both bounds are 0
            dist_errors.append(abs(fast.h[i] - slow.h[i]) * dt / limit.gain)
            row_errors.append(np.abs(fast.G[i] - slow.G[i]).max())
    assert len(dist_errors) > 20, "too few pairs within the detection distance to test"
    assert np.percentile(dist_errors, 95) < 1e-5 and max(dist_errors) < 1.5e-3, dist_errors
    # Rows differ where the closest points are not unique (parallel faces): any pair of
    # witness points on the faces is right, and the two solvers pick different ones.
    assert np.percentile(row_errors, 90) < 1e-6 and max(row_errors) < 0.1, row_errors


def _finger_limit(r, detection=0.03):
    geoms = finger_geoms(r.model)
    fingers = list(geoms)
    pairs = [(geoms[a], geoms[b]) for i, a in enumerate(fingers) for b in fingers[i + 1 :]]
    return CollisionLimit(
        r.model,
        pairs,
        spec=mujoco.MjSpec.from_file(str(mjcf_path(LEAP_HAND.mjcf(r.side)))),
        collision_detection_distance=detection,
        minimum_distance_from_collisions=0.003,
    )


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
    _compare(_finger_limit(r), r.configuration, _hand_samples(r))


def test_rows_are_the_derivative_of_the_distance():
    """For separated pairs, row . dq = -(change of the pair's distance) to first order
    (central finite differences of ``mj_geomDistance`` along random joint directions)."""
    r = LeapRetargeter("right")
    limit, cfg = _finger_limit(r), r.configuration
    rng = np.random.default_rng(5)
    checked, errors = 0, []
    data = mujoco.MjData(r.model)

    def distance_at(x, g1, g2):
        data.qpos[:] = x
        mujoco.mj_kinematics(r.model, data)
        return mujoco.mj_geomDistance(r.model, data, g1, g2, 1.0, None)

    for q in _hand_samples(r, 40, seed=7):
        cfg.update(q)
        hits, dist, _, _, _, _, _ = limit.distances(cfg)
        _, rows, _ = limit.active_rows(cfg, 1.0)
        for hit, d, row in zip(hits, dist, rows, strict=True):
            g1, g2 = limit.geom_id_pairs[hit]
            if d < 0.002:
                continue  # distance is not smooth at contact
            if abs(d - mujoco.mj_geomDistance(r.model, cfg.data, g1, g2, 1.0, None)) > 1e-6:
                continue  # a second contact of the pair, not its closest points
            direction = rng.normal(size=r.model.nv)
            direction /= np.linalg.norm(direction)
            eps = 1e-5
            slope = (
                distance_at(q + eps * direction, g1, g2) - distance_at(q - eps * direction, g1, g2)
            ) / (2 * eps)
            errors.append(abs(-row @ direction - slope) / max(abs(slope), 1e-2))
            checked += 1
    assert checked > 50
    # Closest-feature switches (a face and an edge equally close) break a few derivatives.
    assert np.percentile(errors, 90) < 1e-3, np.percentile(errors, [50, 90, 100])


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


# --------------------------------------------------------------------------- fixtures
def _fixture_env(task):
    import gymnasium as gym

    import beavr_sim  # noqa: F401  (registers the envs)

    env = gym.make(f"beavr_sim/{task}-v0").unwrapped
    env.reset(seed=0)
    return env


def test_fixture_obstacles_are_the_fixtures_where_the_reset_put_them():
    """Each mocap body with colliding geoms is one obstacle; built into a model and placed,
    its geoms are where the env has them (Pour's cup: a cylinder and 16 boxes). A visual-only
    target area is none."""
    from beavr_sim.operator.obstacles import add_obstacles, obstacle_geoms, place_obstacles

    env = _fixture_env("PickupBox")
    assert fixture_obstacles(env.model, env.data) == ()
    env.close()
    env = _fixture_env("Pour")
    obstacles = fixture_obstacles(env.model, env.data)
    assert [o.name for o in obstacles] == ["target_cup"]
    cup = env.task.fixtures["target_cup"]
    assert len(obstacles[0].geoms) == len(cup.geom_ids) == 17
    spec = mujoco.MjSpec()
    add_obstacles(spec, obstacles)
    model = spec.compile()
    data = mujoco.MjData(model)
    place_obstacles(model, data, obstacles)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_kinematics(env.model, env.data)
    ours = obstacle_geoms(model, obstacles)
    np.testing.assert_allclose(data.geom_xpos[ours], env.data.geom_xpos[cup.geom_ids], atol=1e-9)
    np.testing.assert_allclose(data.geom_xmat[ours], env.data.geom_xmat[cup.geom_ids], atol=1e-9)
    np.testing.assert_allclose(model.geom_size[ours], env.model.geom_size[cup.geom_ids])
    env.close()


def test_arm_ik_keeps_the_hand_out_of_a_fixture():
    """Tape's box under the raised hand and a target 15 cm below the hand's home: with the
    fixtures set, the IK stops the hand and forearm at its margin above the box; without, they
    go into it. Setting fixtures of the same shapes again only moves them (no new model)."""
    env = _fixture_env("Tape")
    emb = env.embodiment
    margin = ArmIKConfig().collision_margin
    probe = ArmIK(emb, "right", 1 / 30)
    T = probe.T_world_hand()
    env.task.fixtures["box"].place(env.data, T[:2, 3])
    obstacles = fixture_obstacles(env.model, env.data)
    assert [o.name for o in obstacles] == ["box"]
    probe.set_obstacles(obstacles)
    box = probe.model.geom("obstacle/box/geom0").id
    watched = {g for pair in probe.collision.geom_id_pairs for g in pair if g != box}
    assert {g for pair in probe.collision.geom_id_pairs if box in pair for g in pair} - {box}
    reached = {}
    for with_box in (True, False):
        ik = ArmIK(emb, "right", 1 / 30)
        target = T.copy()
        target[2, 3] += 0.1  # at home the fingertips are 6 mm below the box's top
        for _ in range(60):
            ik.step(target)
        if with_box:
            ik.set_obstacles(obstacles)
        target[2, 3] -= 0.25
        for _ in range(120):
            ik.step(target)
        probe.reset(ik.q)
        data = probe.configuration.data
        reached[with_box] = min(
            mujoco.mj_geomDistance(probe.model, data, g, box, 1.0, None)
            for g in watched
            if probe.model.body(probe.model.geom_bodyid[g]).name.startswith("right/")
        )
    assert reached[True] > margin - 5e-4, reached
    assert reached[False] < 0.0, reached
    # Same shapes, another pose: moved, not rebuilt.
    model = probe.model
    env.task.fixtures["box"].place(env.data, T[:2, 3] + [0.0, 0.3])
    probe.set_obstacles(fixture_obstacles(env.model, env.data))
    assert probe.model is model
    xpos = probe.configuration.data.geom_xpos[box]
    np.testing.assert_allclose(xpos[:2], T[:2, 3] + [0.0, 0.3], atol=1e-9)
    probe.set_obstacles(())  # none: the robot and table only again
    assert probe.model.ngeom == ArmIK(emb, "right", 1 / 30).model.ngeom
    env.close()


def test_recovery_pushes_pairs_inside_the_margin_back_out():
    """Inside ``minimum_distance_from_collisions`` mink's bound is 0 (no deeper); with
    ``recovery`` r the bound is -r (margin - d) / dt: that much of the intrusion must go."""
    r = LeapRetargeter("right")
    cfg = r.configuration
    spec = lambda: mujoco.MjSpec.from_file(str(mjcf_path(LEAP_HAND.mjcf("right"))))  # noqa: E731
    geoms = finger_geoms(r.model)
    fingers = list(geoms)
    pairs = [(geoms[a], geoms[b]) for i, a in enumerate(fingers) for b in fingers[i + 1 :]]
    limits = {
        rec: CollisionLimit(
            r.model,
            pairs,
            spec=spec(),
            collision_detection_distance=0.03,
            minimum_distance_from_collisions=0.003,
            recovery=rec,
        )
        for rec in (0.0, 0.5)
    }
    seen_inside = 0
    for q in _hand_samples(r, 150, seed=3):
        cfg.update(q)
        _, dist, _, _, _, _, _ = limits[0.0].distances(cfg)
        _, _, h0 = limits[0.0].active_rows(cfg, 0.1)
        h0 = h0.copy()
        _, _, h1 = limits[0.5].active_rows(cfg, 0.1)
        inside = dist <= 0.003
        seen_inside += int(inside.sum())
        np.testing.assert_allclose(h0[inside], 0.0)
        np.testing.assert_allclose(h1[inside], -0.5 * (0.003 - dist[inside]) / 0.1)
        np.testing.assert_allclose(h1[~inside], h0[~inside])
    assert seen_inside > 5, "no sampled pair inside the margin: nothing tested"
    with pytest.raises(ValueError, match="recovery"):
        CollisionLimit(r.model, pairs, spec=spec(), recovery=1.5)
