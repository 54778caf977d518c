"""The operator's step QP: bounds and rows handed to ``daqp.solve`` as the caller means them,
failures (any non-positive exit flag) returned as None with the reason kept."""

import daqp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from beavr_sim.operator import qp as qp_module
from beavr_sim.operator.qp import EXIT_NONFINITE, EXITFLAGS, StepQP, exitflag_name


def _random_problem(rng, n, k):
    M = rng.normal(size=(n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    c = rng.normal(size=n)
    A = np.ascontiguousarray(rng.normal(size=(k, n)))
    h = rng.normal(size=k) * 0.05
    return H, c, A, h


def _reference(H, c, A, h, lower, upper):
    """``daqp.solve`` on the problem written out in full (bounds then rows)."""
    n, k = lower.shape[0], h.shape[0]
    bupper, blower = np.concatenate([upper, h]), np.concatenate([lower, np.full(k, -1e30)])
    return daqp.solve(H, c, A, bupper, blower, np.zeros(n + k, np.int32))


def _fill(qp, H, c, lower, upper):
    qp.H[:], qp.c[:], qp.lower[:], qp.upper[:] = H, c, lower, upper


@settings(max_examples=60, deadline=None)
@given(
    n=st.sampled_from([7, 16]),
    k=st.integers(0, 20),
    seed=st.integers(0, 2**32 - 1),
)
def test_feasible_problems_match_daqp_solve(n, k, seed):
    """Rows built around a point inside the bounds (so feasible): the same step as
    ``daqp.solve`` on the problem written out in full, within the bounds and rows."""
    rng = np.random.default_rng(seed)
    H, c, A, _ = _random_problem(rng, n, k)
    lower, upper = -rng.uniform(0.01, 0.2, n), rng.uniform(0.01, 0.2, n)
    x0 = rng.uniform(lower, upper)
    h = A @ x0 + rng.uniform(0.0, 0.05, k)
    qp = StepQP(n, rows_capacity=4)  # k > 4: the bound buffers grow
    _fill(qp, H, c, lower, upper)
    x = qp.solve(A, h)
    x_ref, _, flag, _ = _reference(H, c, A, h, lower, upper)
    assert flag == 1 and qp.last_exitflag == 1
    np.testing.assert_allclose(x, x_ref, atol=1e-10)
    assert np.all(x >= lower - 1e-9) and np.all(x <= upper + 1e-9)
    assert np.all(A @ x <= h + 1e-6)


@pytest.mark.parametrize("n", [7, 16])
def test_reused_qp_matches_daqp_solve_with_failures(n):
    """One StepQP over random problems with 0 to 80 rows (past the initial capacity), some
    infeasible: the same step as ``daqp.solve``, or None with its exit flag where it fails."""
    rng = np.random.default_rng(n)
    qp = StepQP(n, rows_capacity=4)
    failures = 0
    for trial in range(200):
        k = int(rng.integers(0, 80)) if trial % 3 else 0
        H, c, A, h = _random_problem(rng, n, k)
        lower, upper = -rng.uniform(0.01, 0.2, n), rng.uniform(0.01, 0.2, n)
        _fill(qp, H, c, lower, upper)
        x = qp.solve(A, h)
        x_ref, _, flag, _ = _reference(H, c, A, h, lower, upper)
        assert qp.last_exitflag == flag, trial
        assert (x is None) == (flag <= 0), (trial, flag)
        if x is None:
            failures += 1
            continue
        np.testing.assert_allclose(x, x_ref, atol=1e-10)
    assert 0 < failures < 200  # both outcomes were exercised


def test_infeasible_rows_return_none_with_the_exit_flag():
    qp = StepQP(7)
    assert qp.last_exitflag == 0  # no solve yet
    _fill(qp, np.eye(7), np.zeros(7), -0.1, 0.1)
    a = np.arange(1.0, 8.0)
    x = qp.solve(np.stack([a, -a]), np.array([-1.0, -1.0]))  # a x <= -1 and a x >= 1
    assert x is None
    assert qp.last_exitflag == -1 and exitflag_name(qp.last_exitflag) == "infeasible"
    # The next, feasible solve succeeds and resets the flag.
    x = qp.solve(np.zeros((0, 7)), np.zeros(0))
    assert x is not None and qp.last_exitflag == 1
    np.testing.assert_allclose(x, 0.0, atol=1e-12)


def test_nonconvex_cost_returns_none():
    qp = StepQP(7)
    _fill(qp, -np.eye(7), np.ones(7), -0.1, 0.1)
    assert qp.solve(np.zeros((0, 7)), np.zeros(0)) is None
    assert exitflag_name(qp.last_exitflag) == "nonconvex"


@pytest.mark.parametrize("field", ["c", "H"])
def test_a_nan_cost_returns_none_not_a_nan_step(field):
    """DAQP reports success (exit flag 1) with a NaN solution for a NaN cost; the step QP
    must not hand that to the caller (it would be added to the joint positions)."""
    qp = StepQP(7)
    _fill(qp, np.eye(7), np.ones(7), -0.1, 0.1)
    getattr(qp, field)[0] = np.nan
    assert qp.solve(np.zeros((0, 7)), np.zeros(0)) is None
    assert qp.last_exitflag == EXIT_NONFINITE
    assert exitflag_name(EXIT_NONFINITE) == "nonfinite"


@pytest.mark.parametrize("flag", [-2, -3, -4, -6, -7, -8, -42, 0, 1, 2, 4, 5])
def test_every_exit_flag_is_checked(monkeypatch, flag):
    """Whatever non-positive exit flag DAQP returns (with whatever it left in x), the solve
    returns None and records it, no exception; positive flags are solutions."""
    calls = []

    def fake_solve(H, f, A, bupper, blower, sense):
        calls.append((A.shape, bupper.shape, blower.shape, sense.shape))
        return np.full(H.shape[0], 0.01), 0.0, flag, {}

    monkeypatch.setattr(qp_module.daqp, "solve", fake_solve)
    qp = StepQP(7)
    _fill(qp, np.eye(7), np.zeros(7), -0.1, 0.1)
    x = qp.solve(np.zeros((3, 7)), np.ones(3))
    assert qp.last_exitflag == flag
    assert calls == [((3, 7), (10,), (10,), (10,))]
    if flag > 0:
        np.testing.assert_allclose(x, 0.01)
    else:
        assert x is None


def test_exit_flag_names_cover_daqps_flags():
    assert all(EXITFLAGS[f] for f in (1, 2, 3, 4, 5, -1, -2, -3, -4, -5, -6, -7, -8))
    assert all(f > 0 for f, name in EXITFLAGS.items() if "optimal" in name)


def test_each_solve_returns_a_new_array():
    """Callers change the step in place (held fingers set to 0): that must not touch the
    next solve's result."""
    qp = StepQP(7)
    _fill(qp, np.eye(7), -np.ones(7), -0.1, 0.1)
    first = qp.solve(np.zeros((0, 7)), np.zeros(0))
    first[:] = 5.0
    second = qp.solve(np.zeros((0, 7)), np.zeros(0))
    np.testing.assert_allclose(second, 0.1)


def test_step_qp_rejects_an_empty_problem():
    with pytest.raises(ValueError, match="at least one variable"):
        StepQP(0)


def test_step_qp_takes_strided_and_float32_rows():
    """Rows that are a strided view (a column subset), or float32, are solved as their
    contiguous float64 copy; rows of the wrong shape are a caller's bug and raise."""
    rng = np.random.default_rng(7)
    H, c, _, h = _random_problem(rng, 7, 6)
    h = np.abs(h)
    A = rng.normal(size=(6, 12))[:, :7]
    assert not A.flags["C_CONTIGUOUS"]
    qp = StepQP(7)
    _fill(qp, H, c, -0.1, 0.1)
    x_ref, _, flag, _ = _reference(
        H, c, np.ascontiguousarray(A), h, np.full(7, -0.1), np.full(7, 0.1)
    )
    assert flag == 1
    np.testing.assert_allclose(qp.solve(A, h), x_ref, atol=1e-10)
    A32 = np.ascontiguousarray(A, dtype=np.float32)
    x_ref32, _, _, _ = _reference(
        H, c, A32.astype(np.float64), h, np.full(7, -0.1), np.full(7, 0.1)
    )
    np.testing.assert_allclose(qp.solve(A32, h), x_ref32, atol=1e-10)
    with pytest.raises(ValueError, match="rows A need shape"):
        qp.solve(np.zeros((2, 5)), np.zeros(2))
    # No rows must still say how many variables: daqp.solve reads n from A's columns.
    with pytest.raises(ValueError, match="rows A need shape"):
        qp.solve(np.zeros((0, 0)), np.zeros(0))
