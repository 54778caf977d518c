"""The one joint rate limit (:mod:`beavr_sim.twin.rate_limit`): no joint faster than its cap,
a reachable target unchanged, the mask exactly the shortened joints, a non-finite target held;
and its users (the twin's step limit, the guard's velocity rule, the mirror) share it."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from beavr_sim.twin.rate_limit import ROUNDING_TOLERANCE, JointRateLimit

N = 6
positions = st.floats(-10.0, 10.0, allow_nan=False)
speeds = st.floats(0.01, 20.0)
intervals = st.floats(1e-4, 0.1)
#: A target joint: near the cap (the boundary), far, unchanged, or not a number.
targets = st.one_of(
    positions,
    st.floats(-0.1, 0.1),  # added to previous below: mostly within reach
    st.sampled_from([math.nan, math.inf, -math.inf]),
)


def _slack(previous: np.ndarray) -> np.ndarray:
    """The rounding of ``previous + step`` (a few units in the last place of the sum)."""
    return 4 * np.finfo(float).eps * np.maximum(np.abs(previous), 1.0)


@st.composite
def cases(draw, grouped: bool):
    vmax = np.array(draw(st.lists(speeds, min_size=N, max_size=N)))
    previous = np.array(draw(st.lists(positions, min_size=N, max_size=N)))
    target = np.array(draw(st.lists(targets, min_size=N, max_size=N)))
    near = np.array(draw(st.lists(st.booleans(), min_size=N, max_size=N)))
    target = np.where(near & np.isfinite(target), previous + target, target)
    dt = draw(intervals)
    groups: list[list[int]] = []
    if grouped:
        order = draw(st.permutations(range(N)))
        cuts = sorted(draw(st.lists(st.integers(0, N), max_size=3)))
        bounds = [0, *cuts, N]
        groups = [list(order[a:b]) for a, b in itertools.pairwise(bounds) if b > a]
        groups = groups[: draw(st.integers(0, len(groups)))]  # some joints alone
    return JointRateLimit.of(vmax, groups), previous, target, dt


@settings(max_examples=300, deadline=None)
@given(case=cases(grouped=False))
def test_each_joint_is_clamped_to_its_reach_and_only_the_clamped_ones_are_marked(case):
    limit, previous, target, dt = case
    result = limit.clamp(previous, target, dt)
    reach = limit.reach(dt)
    finite = np.isfinite(target)
    moved = np.abs(result.target - previous)
    assert np.isfinite(result.target).all()
    assert (moved <= reach * (1 + ROUNDING_TOLERANCE) + _slack(previous)).all(), "too fast"
    np.testing.assert_array_equal(result.non_finite, ~finite)
    np.testing.assert_array_equal(result.target[~finite], previous[~finite])  # held
    beyond = finite & (np.abs(target - previous) > reach * (1 + ROUNDING_TOLERANCE))
    np.testing.assert_array_equal(result.limited, beyond)
    within = finite & ~beyond
    np.testing.assert_array_equal(result.target[within], target[within])  # unchanged
    # A clamped joint stops exactly at its reach, towards the target.
    sign = np.sign(target[beyond] - previous[beyond])
    np.testing.assert_array_equal(result.target[beyond], previous[beyond] + sign * reach[beyond])


@settings(max_examples=300, deadline=None)
@given(case=cases(grouped=True))
def test_a_group_is_shortened_along_its_direction(case):
    """Joints of a group move together: when one is beyond reach, the group's step is scaled
    down as a whole (no joint faster than its cap, the target on the line to the command);
    the mask marks the group's moving joints; joints alone are clamped on their own."""
    limit, previous, target, dt = case
    result = limit.clamp(previous, target, dt)
    reach = limit.reach(dt)
    held = np.where(np.isfinite(target), target, previous)
    step = held - previous
    moved = result.target - previous
    assert (np.abs(moved) <= reach * (1 + ROUNDING_TOLERANCE) + _slack(previous)).all()
    alone = np.ones(N, dtype=bool)
    for group in limit.groups:
        g = list(group)
        alone[g] = False
        beyond = (np.abs(step[g]) > reach[g] * (1 + ROUNDING_TOLERANCE)).any()
        if not beyond:
            np.testing.assert_array_equal(result.target[g], held[g])
            assert not result.limited[g].any()
            continue
        np.testing.assert_array_equal(result.limited[g], step[g] != 0)
        scale = np.abs(moved[g]).sum() / np.abs(step[g]).sum()
        assert 0 < scale < 1
        np.testing.assert_allclose(moved[g], scale * step[g], rtol=1e-9, atol=1e-12)
    beyond = alone & (np.abs(step) > reach * (1 + ROUNDING_TOLERANCE))
    np.testing.assert_array_equal(result.limited[alone], beyond[alone])
    np.testing.assert_array_equal(result.target[alone & ~beyond], held[alone & ~beyond])


def test_an_infinite_cap_never_limits_and_no_time_lets_nothing_move():
    limit = JointRateLimit.of([1.0, math.inf], groups=[[0, 1]])
    result = limit.clamp(np.zeros(2), np.array([0.5, 100.0]), 0.1)
    np.testing.assert_allclose(result.target, [0.1, 20.0])  # the group scaled by joint 0
    free = JointRateLimit.of([math.inf, 2.0])
    result = free.clamp(np.zeros(2), np.array([100.0, 1.0]), 0.1)
    np.testing.assert_allclose(result.target, [100.0, 0.2])
    np.testing.assert_array_equal(result.limited, [False, True])
    for dt in (0.0, -1.0):
        result = free.clamp(np.ones(2), np.array([2.0, 1.0]), dt)
        np.testing.assert_array_equal(result.target, [2.0, 1.0])  # the inf cap still moves
        result = JointRateLimit.of([1.0, 1.0]).clamp(np.ones(2), np.array([2.0, 1.0]), dt)
        np.testing.assert_array_equal(result.target, [1.0, 1.0])
        np.testing.assert_array_equal(result.limited, [True, False])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"max_velocity": (1.0, 0.0)}, "max_velocity must be > 0"),
        ({"max_velocity": (1.0, math.nan)}, "max_velocity must be > 0"),
        ({"max_velocity": (1.0,), "tolerance": -1.0}, "tolerance"),
        ({"max_velocity": (1.0, 1.0), "groups": ((0, 2),)}, "valid are 0 .. 1"),
        ({"max_velocity": (1.0, 1.0), "groups": ((0,), (0, 1))}, "more than one group"),
    ],
)
def test_a_bad_limit_is_refused_with_what_is_valid(kwargs, match):
    with pytest.raises(ValueError, match=match):
        JointRateLimit(**kwargs)


def test_arrays_of_the_wrong_length_are_refused_not_read_past():
    limit = JointRateLimit.of([1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"target has shape \(2,\), not \(3,\)"):
        limit.clamp(np.zeros(3), np.zeros(2), 0.1)
    with pytest.raises(ValueError, match=r"previous has shape \(4,\)"):
        limit.clamp(np.zeros(4), np.zeros(3), 0.1)
    with pytest.raises(ValueError, match="step has shape"):
        limit.exceeds(np.zeros((3, 1)), 0.1)
