"""After a forced 1 s guard hold on the PickupBox trace, the operator's arm IK must not drive
into a pose the twin's guard refuses (the forearm against the shoulder, the elbow behind the
guard's workspace box), or the loop resyncs it to the held action, it takes the same step and
the arm stays stuck for the rest of the episode."""

from __future__ import annotations

import pytest

from beavr_sim.operator.arm_ik import ArmIK
from beavr_sim.robots.embodiment import EMBODIMENTS, Embodiment


@pytest.mark.parametrize("t0", [0.5, 1.0, 1.5, 2.0])
def test_the_arm_is_not_stuck_after_a_forced_hold(t0, pickup_box_with_forced_hold):
    loop, refusals = pickup_box_with_forced_hold(t0, t0 + 1.0)
    held: list[bool] = []
    loop.listeners.append(lambda tick: held.append("right" in tick.state.guard_blocked_effectors))
    summary = loop.run()
    first = held.index(True)
    assert sum(held[first : first + 30]) >= 29, "the forced hold did not last 1 s"
    after = sum(held[first + 30 :])
    assert after <= 5, f"{after} refusals after the release, e.g. {refusals[:3]}"
    assert summary.success


@pytest.mark.parametrize("name", sorted(EMBODIMENTS))
def test_the_ik_watches_the_arm_links_the_guard_checks(name):
    """Every embodiment's IK keeps non-adjacent arm links apart and off the guard box's back
    face, except geom pairs already within the margin at home (the RX-1's forearm and wrist
    roll overlap there; its MJCF excludes them, so the guard does not check them either)."""
    embodiment = Embodiment(EMBODIMENTS[name])
    for effector in embodiment.effectors:
        ik = ArmIK(embodiment, effector.name, 1 / 30)
        model, p = ik.model, effector.name + "/"
        bodies = {
            frozenset(model.body(model.geom_bodyid[g]).name[len(p) :] for g in pair)
            for pair in ik.self_collision_pairs
        }
        assert bodies, "no self-collision pairs"
        assert all(len(b) == 2 for b in bodies)
        assert ik.wall_pairs
        pairs = {frozenset(p) for p in ik.collision.geom_id_pairs}
        assert {frozenset(p) for p in ik.self_collision_pairs} <= pairs
        # mink drops a link whose weld parent is the wall's (the world's) child, e.g. link1.
        assert any(frozenset(p) in pairs for p in ik.wall_pairs)
        if "xarm7" in name:
            assert frozenset(("link1", "link5")) in bodies  # forearm against the shoulder
        else:
            assert frozenset(("forearm", "wrist_roll")) not in bodies
        # Nothing watched is within the margin at home: the IK is free to move from there.
        ik.reset(ik.joints.home)
        _, dist, *_ = ik.collision.distances(ik.configuration)
        assert (dist > ik.config.collision_margin).all()
