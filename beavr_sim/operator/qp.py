"""The operator's per-tick QP: a step ``dq`` under simple bounds and a few inequality rows,
solved by DAQP (``daqp.solve``) from preallocated arrays.

Both of the operator's solvers (arm IK, LEAP retargeting) solve, once or a few times per
control tick,

    minimise 1/2 dq^T H dq + c^T dq   s.t.   lower <= dq <= upper,   A dq <= h

with H, c and the bounds from their tasks (:mod:`beavr_sim.operator.kernels` fills them in
place) and the rows from collision avoidance (a varying number, often none). Allocating these
arrays afresh every tick, and handing new arrays back from compiled code, cost more than the
arithmetic that fills them; :class:`StepQP` keeps them instead, and stacks the bounds into
DAQP's form (``bupper``, ``blower``, ``sense``) in buffers it keeps too.

The solve goes through DAQP's Python wrapper, ``daqp.solve``, with its default settings. An
earlier version called the C function ``daqp_quadprog`` through ctypes with hand-packed
structs: it saved 6-10 us per solve, 15-40 us of a 0.2-0.4 ms operator tick (one arm and one
hand QP per tick; about 0.1% of the 33 ms control period), but its struct layout had to
follow DAQP's releases (the settings struct grew three fields in recent ones) and nothing
but a test at construction could tell when it did not.

A solve that DAQP does not finish with a positive exit flag (infeasible rows, e.g. a
configuration already in collision; an iteration limit; a non-convex H) returns None and the
caller holds; :attr:`StepQP.last_exitflag` keeps the reason (:data:`EXITFLAGS` names them).
"""

from __future__ import annotations

import math

import daqp
import numpy as np

from beavr_sim.operator import kernels

#: :attr:`StepQP.last_exitflag` when DAQP reported success but the step is not finite (NaN or
#: inf in H, c or the bounds; DAQP returns exit flag 1 with a NaN solution for a NaN cost).
EXIT_NONFINITE = -100
#: DAQP's exit flags (``constants.h``, DAQP 0.11) and this module's own, by value. Positive:
#: a solution (:meth:`StepQP.solve` returns it); otherwise none (it returns None).
EXITFLAGS = {
    5: "feasible",  # branch and bound stopped early (not used by these QPs)
    4: "optimal_inexact",
    3: "constrained_point",  # hierarchical QPs (not used here)
    2: "soft_optimal",
    1: "optimal",
    -1: "infeasible",
    -2: "cycling",
    -3: "unbounded",
    -4: "iteration_limit",
    -5: "nonconvex",
    -6: "overdetermined_initial_active_set",
    -7: "time_limit",
    -8: "unsupported",
    EXIT_NONFINITE: "nonfinite",
}


_FLOAT64 = np.dtype(np.float64)


def exitflag_name(flag: int) -> str:
    """A readable name of a DAQP exit flag (or of :data:`EXIT_NONFINITE`)."""
    return EXITFLAGS.get(int(flag), f"exitflag_{int(flag)}")


class StepQP:
    """The arrays of one ``n``-variable step QP, and its solve.

    Fill :attr:`H`, :attr:`c`, :attr:`lower` and :attr:`upper` (in place), then call
    :meth:`solve` with the inequality rows. The bound buffers grow when a tick has more rows
    than any before it. :attr:`last_exitflag`: DAQP's exit flag of the latest solve (0 before
    the first).
    """

    def __init__(self, n: int, rows_capacity: int = 32):
        if n < 1:
            raise ValueError(f"a step QP needs at least one variable, got n={n}")
        self.n = int(n)
        self.H = np.zeros((self.n, self.n))
        self.c = np.zeros(self.n)
        self.lower = np.zeros(self.n)
        self.upper = np.zeros(self.n)
        self.last_exitflag = 0
        self._allocate(rows_capacity)

    def _allocate(self, rows_capacity: int) -> None:
        m = self.n + max(int(rows_capacity), 0)
        self._bupper = np.empty(m)
        self._blower = np.empty(m)
        self._sense = np.zeros(m, dtype=np.int32)

    def solve(self, A: np.ndarray, h: np.ndarray) -> np.ndarray | None:
        """The step ``dq`` (a new array), or None when DAQP finds no solution (see
        :attr:`last_exitflag` for why): the caller holds.

        ``A``: k x n rows, ``h``: their k upper bounds. Raises ValueError for rows of the
        wrong shape (a caller's bug, not a solver failure)."""
        n, k = self.n, h.shape[0]
        if A.shape != (k, n):
            # daqp.solve takes n from A's columns: a wrong shape would solve another problem.
            raise ValueError(f"rows A need shape ({k}, {n}), got {A.shape}")
        if A.dtype != _FLOAT64 or not A.flags.c_contiguous:
            A = np.ascontiguousarray(A, dtype=np.float64)
        m = n + k
        if m > self._bupper.shape[0]:
            self._allocate(2 * k)
        filled = kernels.stack_bounds(
            self.lower, self.upper, h, self._bupper, self._blower, self._sense
        )
        if filled != m:
            raise AssertionError(f"StepQP: bound buffers too short for {m} constraints")
        dq, _, exitflag, _ = daqp.solve(
            self.H, self.c, A, self._bupper[:m], self._blower[:m], self._sense[:m]
        )
        if exitflag > 0 and not math.isfinite(dq.dot(dq)):  # NaN or inf anywhere in dq
            exitflag = EXIT_NONFINITE
        self.last_exitflag = int(exitflag)
        return dq if exitflag > 0 else None
