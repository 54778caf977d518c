"""The operator's per-tick QP: a step ``dq`` under simple bounds and a few inequality rows,
solved by DAQP into preallocated arrays.

Both of the operator's solvers (arm IK, LEAP retargeting) solve, once or a few times per
control tick,

    minimise 1/2 dq^T H dq + c^T dq   s.t.   lower <= dq <= upper,   A dq <= h

with H, c and the bounds from their tasks (:mod:`beavr_sim.operator.kernels` fills them in
place) and the rows from collision avoidance (a varying number, often none). Allocating these
arrays afresh every tick, and handing new arrays back from compiled code, cost more than the
arithmetic that fills them; :class:`StepQP` keeps them instead.

The solve itself is DAQP's ``daqp_quadprog``. Its Python wrapper ``daqp.solve`` spends about
ten microseconds per call building the problem, settings and result structs (more than DAQP
takes on these 7- and 16-variable problems), so for the DAQP versions whose C structs are
known (:data:`DAQP_LAYOUT_VERSIONS`) :class:`StepQP` fills the three structs in preallocated
buffers and calls ``daqp_quadprog`` directly, with the wrapper's default settings. At
construction it solves test problems both ways and falls back to ``daqp.solve`` (with a
warning) if they differ; ``direct=False`` forces the wrapper.
"""

from __future__ import annotations

import ctypes
import functools
import importlib.metadata
import inspect
import logging

import daqp
import numpy as np

from beavr_sim.operator import kernels

log = logging.getLogger(__name__)

#: DAQP releases whose ``DAQPProblem`` / ``DAQPSettings`` / ``DAQPResult`` layouts the direct
#: call writes (from DAQP's ``types.h`` and ``api.h``).
DAQP_LAYOUT_VERSIONS = frozenset({"0.11.0"})
#: Field order of ``DAQPSettings`` (doubles, except the ints named in _SETTINGS_INTS).
_SETTINGS_FIELDS = (
    "primal_tol", "dual_tol", "zero_tol", "pivot_tol", "progress_tol", "cycle_tol",
    "iter_limit", "fval_bound", "eps_prox", "eta_prox", "rho_soft", "rel_subopt",
    "abs_subopt", "sing_tol", "refactor_tol", "time_limit", "w_soft", "eq_reduction",
    "presolve",
)  # fmt: skip
_SETTINGS_INTS = frozenset({"cycle_tol", "iter_limit", "eq_reduction", "presolve"})
_PROBLEM_BYTES, _SETTINGS_BYTES, _RESULT_BYTES = 80, 136, 64


@functools.cache
def _quadprog():
    """ctypes handle of ``daqp_quadprog`` for a DAQP release with a known layout, or None."""
    try:
        version = importlib.metadata.version("daqp")
    except importlib.metadata.PackageNotFoundError:
        return None
    if version not in DAQP_LAYOUT_VERSIONS:
        log.info("daqp %s: solving through daqp.solve (struct layout not known)", version)
        return None
    try:
        function = ctypes.CDLL(daqp.__file__).daqp_quadprog
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_void_p] * 3
    function.restype = None
    return function


def _settings_buffer() -> np.ndarray:
    """``DAQPSettings`` with ``daqp.solve``'s defaults (read from its signature)."""
    defaults = inspect.signature(daqp.solve).parameters
    buffer = np.zeros(_SETTINGS_BYTES, dtype=np.uint8)
    offset = 0
    for name in _SETTINGS_FIELDS:
        if name in _SETTINGS_INTS:
            buffer[offset : offset + 4].view(np.int32)[0] = int(defaults[name].default)
            offset += 4
        else:
            offset += -offset % 8  # doubles are 8-byte aligned
            buffer[offset : offset + 8].view(np.float64)[0] = float(defaults[name].default)
            offset += 8
    if offset != _SETTINGS_BYTES:
        raise AssertionError(f"DAQPSettings layout: {offset} bytes, expected {_SETTINGS_BYTES}")
    return buffer


class StepQP:
    """The arrays of one ``n``-variable step QP, and its solve.

    Fill :attr:`H`, :attr:`c`, :attr:`lower` and :attr:`upper` (in place), then call
    :meth:`solve` with the inequality rows. The bound arrays grow when a tick has more rows
    than any before it. ``direct``: call DAQP's C solver directly when its layout is known
    (the default), else through ``daqp.solve``.
    """

    def __init__(self, n: int, rows_capacity: int = 32, direct: bool = True):
        if n < 1:
            raise ValueError(f"a step QP needs at least one variable, got n={n}")
        self.n = int(n)
        self.H = np.zeros((self.n, self.n))
        self.c = np.zeros(self.n)
        self.lower = np.zeros(self.n)
        self.upper = np.zeros(self.n)
        self._x = np.zeros(self.n)
        self._allocate(rows_capacity)
        self._quadprog = _quadprog() if direct else None
        if self._quadprog is not None:
            self._problem = np.zeros(_PROBLEM_BYTES // 8, dtype=np.int64)
            self._settings = _settings_buffer()
            self._result = np.zeros(_RESULT_BYTES // 8, dtype=np.int64)
            self._args = (self._result.ctypes.data, self._problem.ctypes.data,
                          self._settings.ctypes.data)  # fmt: skip
            if not self._direct_matches_wrapper():
                log.warning("DAQP's direct call disagrees with daqp.solve: using daqp.solve")
                self._quadprog = None

    @property
    def direct(self) -> bool:
        """Whether solves call DAQP's C solver directly (else ``daqp.solve``)."""
        return self._quadprog is not None

    def _allocate(self, rows_capacity: int) -> None:
        m = self.n + max(int(rows_capacity), 0)
        self._bupper = np.empty(m)
        self._blower = np.empty(m)
        self._sense = np.zeros(m, dtype=np.int32)
        self._lam = np.zeros(m)

    def solve(self, A: np.ndarray, h: np.ndarray) -> np.ndarray | None:
        """The step ``dq`` (an array of this QP's, valid until its next solve), or None when
        DAQP finds no solution (infeasible rows, e.g. a configuration already in
        collision): the caller holds.

        ``A``: k x n rows (float64, C-contiguous), ``h``: their k upper bounds."""
        if self.n + h.shape[0] > self._bupper.shape[0]:
            self._allocate(2 * h.shape[0])
        if self._quadprog is None:
            m = kernels.stack_bounds(
                self.lower, self.upper, h, self._bupper, self._blower, self._sense
            )
            dq, _, exitflag, _ = daqp.solve(
                self.H, self.c, A, self._bupper[:m], self._blower[:m], self._sense[:m]
            )
            return dq if exitflag > 0 else None
        args = (self.lower, self.upper, h, self._bupper, self._blower, self._sense, self._x,
                self._lam, self._problem, self._result)  # fmt: skip
        if kernels.daqp_problem(self.H, self.c, A, *args) < 0:
            A = np.ascontiguousarray(A, dtype=np.float64)
            if A.shape != (h.shape[0], self.n):
                raise ValueError(f"rows A need shape ({h.shape[0]}, {self.n}), got {A.shape}")
            kernels.daqp_problem(self.H, self.c, A, *args)
        self._quadprog(*self._args)
        return self._x if kernels.daqp_exitflag(self._result) > 0 else None

    def _direct_matches_wrapper(self) -> bool:
        """Solve a few random problems (with rows, without, infeasible) both ways."""
        rng = np.random.default_rng(0)
        n = self.n
        for k, feasible in ((0, True), (3, True), (n + 2, True), (2, False)):
            M = rng.normal(size=(n, n))
            H = M @ M.T + n * np.eye(n)
            c = rng.normal(size=n)
            A = np.ascontiguousarray(rng.normal(size=(k, n)))
            h = np.abs(rng.normal(size=k)) * 0.1
            if not feasible:  # a x <= -1 and -a x <= -1
                A[1] = -A[0]
                h[:] = -1.0
            lower, upper = -0.5 * np.ones(n), 0.5 * np.ones(n)
            bupper = np.concatenate([upper, h])
            blower = np.concatenate([lower, np.full(k, -1e30)])
            x_ref, _, flag_ref, _ = daqp.solve(H, c, A, bupper, blower, np.zeros(n + k, np.int32))
            self.H[:], self.c[:], self.lower[:], self.upper[:] = H, c, lower, upper
            x = self.solve(A, h)
            if (x is None) != (flag_ref <= 0):
                return False
            if x is not None and not np.allclose(x, x_ref, atol=1e-9):
                return False
        return True
