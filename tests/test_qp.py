"""The operator's step QP: DAQP called directly matches ``daqp.solve``."""

import importlib.metadata

import daqp
import numpy as np
import pytest

from beavr_sim.operator.qp import DAQP_LAYOUT_VERSIONS, StepQP


def _random_problem(rng, n, k):
    M = rng.normal(size=(n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    c = rng.normal(size=n)
    A = np.ascontiguousarray(rng.normal(size=(k, n)))
    h = rng.normal(size=k) * 0.05
    return H, c, A, h


def test_direct_call_is_used_for_known_daqp_layouts():
    known = importlib.metadata.version("daqp") in DAQP_LAYOUT_VERSIONS
    assert StepQP(7).direct == known
    assert not StepQP(7, direct=False).direct


@pytest.mark.parametrize("n", [7, 16])
def test_step_qp_matches_daqp_solve(n):
    """Random problems with 0 to 80 rows (past the initial capacity: the buffers grow),
    some infeasible: same solution, or None where daqp.solve fails."""
    rng = np.random.default_rng(n)
    qp = StepQP(n, rows_capacity=4)
    failures = 0
    for trial in range(200):
        k = int(rng.integers(0, 80)) if trial % 3 else 0
        H, c, A, h = _random_problem(rng, n, k)
        lower, upper = -rng.uniform(0.01, 0.2, n), rng.uniform(0.01, 0.2, n)
        qp.H[:], qp.c[:], qp.lower[:], qp.upper[:] = H, c, lower, upper
        x = qp.solve(A, h)
        bupper, blower = np.concatenate([upper, h]), np.concatenate([lower, np.full(k, -1e30)])
        x_ref, _, flag, _ = daqp.solve(H, c, A, bupper, blower, np.zeros(n + k, np.int32))
        assert (x is None) == (flag <= 0), (trial, flag)
        if x is None:
            failures += 1
            continue
        np.testing.assert_allclose(x, x_ref, atol=1e-10)
        assert np.all(x >= lower - 1e-9) and np.all(x <= upper + 1e-9)
        assert np.all(A @ x <= h + 1e-6)
    assert 0 < failures < 200  # both outcomes were exercised


def test_step_qp_rejects_an_empty_problem():
    with pytest.raises(ValueError, match="at least one variable"):
        StepQP(0)


def test_step_qp_takes_strided_rows():
    """Rows that are a strided view (a column subset) are solved as their contiguous copy."""
    rng = np.random.default_rng(7)
    H, c, _, h = _random_problem(rng, 7, 6)
    A = rng.normal(size=(6, 12))[:, :7]
    assert not A.flags["C_CONTIGUOUS"]
    qp = StepQP(7)
    qp.H[:], qp.c[:], qp.lower[:], qp.upper[:] = H, c, -0.1, 0.1
    x = qp.solve(A, np.abs(h))
    x_ref, _, flag, _ = daqp.solve(
        H, c, np.ascontiguousarray(A), np.concatenate([np.full(7, 0.1), np.abs(h)]),
        np.concatenate([np.full(7, -0.1), np.full(6, -1e30)]), np.zeros(13, np.int32),
    )  # fmt: skip
    assert flag > 0
    np.testing.assert_allclose(x, x_ref, atol=1e-10)
    with pytest.raises(ValueError, match="rows A need shape"):
        qp.solve(np.zeros((2, 5)), np.zeros(2))
