"""The operator's per-tick QP: a step ``dq`` under simple bounds and a few inequality rows,
solved by DAQP into preallocated arrays.

Both of the operator's solvers (arm IK, LEAP retargeting) solve, once or a few times per
control tick,

    minimise 1/2 dq^T H dq + c^T dq   s.t.   lower <= dq <= upper,   A dq <= h

with H, c and the bounds from their tasks (:mod:`beavr_sim.teleop.kernels` fills them in
place) and the rows from collision avoidance (a varying number, often none). Allocating these
arrays afresh every tick, and handing new arrays back from compiled code, cost more than the
arithmetic that fills them; :class:`StepQP` keeps them instead.
"""

from __future__ import annotations

import daqp
import numpy as np

from beavr_sim.teleop import kernels


class StepQP:
    """The arrays of one ``n``-variable step QP, and its solve.

    Fill :attr:`H`, :attr:`c`, :attr:`lower` and :attr:`upper` (in place), then call
    :meth:`solve` with the inequality rows. The bound arrays grow when a tick has more rows
    than any before it.
    """

    def __init__(self, n: int, rows_capacity: int = 32):
        if n < 1:
            raise ValueError(f"a step QP needs at least one variable, got n={n}")
        self.n = int(n)
        self.H = np.zeros((self.n, self.n))
        self.c = np.zeros(self.n)
        self.lower = np.zeros(self.n)
        self.upper = np.zeros(self.n)
        self._allocate(rows_capacity)

    def _allocate(self, rows_capacity: int) -> None:
        m = self.n + max(int(rows_capacity), 0)
        self._bupper = np.empty(m)
        self._blower = np.empty(m)
        self._sense = np.zeros(m, dtype=np.int32)

    def solve(self, A: np.ndarray, h: np.ndarray) -> np.ndarray | None:
        """The step ``dq`` (a new array), or None when DAQP finds no solution (infeasible
        rows, e.g. a configuration already in collision): the caller holds.

        ``A``: k x n rows (C-contiguous), ``h``: their k upper bounds."""
        m = kernels.stack_bounds(self.lower, self.upper, h, self._bupper, self._blower, self._sense)
        if m < 0:
            self._allocate(2 * h.shape[0])
            m = kernels.stack_bounds(
                self.lower, self.upper, h, self._bupper, self._blower, self._sense
            )
        dq, _, exitflag, _ = daqp.solve(
            self.H, self.c, A, self._bupper[:m], self._blower[:m], self._sense[:m]
        )
        return dq if exitflag > 0 else None
