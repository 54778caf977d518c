"""One joint rate limit: how far each joint may move in a time, and a target clamped to it.

:class:`JointRateLimit` holds a speed cap per joint (rad/s, action order). ``clamp(previous,
target, dt)`` returns the target each joint can reach from ``previous`` within ``dt`` at its
cap, and which joints that shortened (:class:`RateLimited`). Every speed cap of the pipeline is
this one object: the twin's per-tick step limit, the guard's velocity rule (it refuses what
:meth:`JointRateLimit.exceeds` marks), the hardware mirror's rate limit and its catch-up. The
counters stay with those callers; the arithmetic lives here.

Contract:

- no joint of the result is further than ``reach(dt) * (1 + tolerance)`` from ``previous``
  (up to the rounding of adding the step to ``previous``); a joint within that is returned
  unchanged (``tolerance``: a step already at the cap, rounded, is not a limited one);
- a non-finite target (NaN, inf) holds ``previous`` for that joint (``non_finite``), never
  raises; ``previous`` itself is trusted (the caller's last applied target);
- joints of one group (``groups``, e.g. the joints of one device) move together: when any of
  them is beyond reach the whole group's step is shortened along its direction, so the target
  stays on the line to the commanded one; other joints are clamped each on its own;
- a cap of ``math.inf`` never limits its joint; a ``dt`` of zero or less lets nothing move.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numba
import numpy as np

#: Relative slack before a step counts as beyond reach: a step clamped to the cap and then
#: re-measured (after a subtraction, or over a slightly different interval) is not limited
#: again.
ROUNDING_TOLERANCE = 1e-9

_jit = numba.njit(cache=True, nogil=True)


@_jit
def _over(step, reach, slack):
    """A step beyond reach, past the rounding slack (False for a non-finite step)."""
    return abs(step) > reach * slack


@_jit
def _clamp_joints(previous, target, reach, slack, out, limited, non_finite):
    """Each joint on its own: ``out`` the target clamped to ``previous`` +- ``reach`` where
    it is beyond reach (``limited``), ``previous`` where it is not finite (``non_finite``)."""
    for i in range(out.shape[0]):
        p, q, r = previous[i], target[i], reach[i]
        bad = not math.isfinite(q)
        over = not bad and _over(q - p, r, slack)
        non_finite[i], limited[i] = bad, over
        if bad:
            out[i] = p
        elif over:
            out[i] = min(max(q, p - r), p + r)
        else:
            out[i] = q


@_jit
def _beyond(step, reach, slack, out):
    for i in range(out.shape[0]):
        out[i] = _over(step[i], reach[i], slack)


_warm: list[bool] = []


def _warm_up() -> None:
    """Compile (or load from numba's disk cache) the kernels once per process, so that no
    command pays for it."""
    if not _warm:
        x, flags = np.zeros(1), np.zeros(1, dtype=np.bool_)
        _clamp_joints(x, x, x, 1.0, x.copy(), flags, flags.copy())
        _beyond(x, x, 1.0, flags)
        _warm.append(True)


@dataclass(frozen=True, eq=False)
class RateLimited:
    """The result of :meth:`JointRateLimit.clamp` (arrays in the limit's joint order)."""

    #: The reachable target (a new array; ``previous`` where the target was non-finite).
    target: np.ndarray
    #: Joints whose finite target was beyond reach and was shortened.
    limited: np.ndarray
    #: Joints whose target was NaN or inf (held at ``previous``).
    non_finite: np.ndarray


@dataclass(frozen=True)
class JointRateLimit:
    """A speed cap per joint (rad/s; ``math.inf``: not limited), the joint groups that move
    together (indices; each joint in at most one group) and the rounding ``tolerance``."""

    max_velocity: tuple[float, ...]
    groups: tuple[tuple[int, ...], ...] = ()
    tolerance: float = ROUNDING_TOLERANCE
    _vmax: np.ndarray = field(init=False, repr=False, compare=False)
    _groups: tuple[np.ndarray, ...] = field(init=False, repr=False, compare=False)
    #: ``[(dt, reach)]`` of the last call (one tuple, swapped whole).
    _reach: list = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        vmax = np.array(self.max_velocity, dtype=np.float64).reshape(-1)
        bad = [v for v in self.max_velocity if not v > 0]
        if bad:
            raise ValueError(f"max_velocity must be > 0 rad/s (or math.inf) per joint, got {bad}")
        if not (self.tolerance >= 0 and math.isfinite(self.tolerance)):
            raise ValueError(f"tolerance must be a finite number >= 0, got {self.tolerance!r}")
        seen: set[int] = set()
        for group in self.groups:
            for i in group:
                if not (isinstance(i, (int, np.integer)) and 0 <= i < vmax.size):
                    raise ValueError(
                        f"group index {i!r} is not a joint: valid are 0 .. {vmax.size - 1}"
                    )
                if i in seen:
                    raise ValueError(f"joint {i} is in more than one group: {self.groups}")
                seen.add(int(i))
        vmax.setflags(write=False)
        object.__setattr__(self, "_vmax", vmax)
        object.__setattr__(
            self, "_groups", tuple(np.array(g, dtype=np.int64) for g in self.groups if len(g))
        )
        object.__setattr__(self, "_reach", [(None, None)])
        _warm_up()

    @classmethod
    def of(
        cls,
        max_velocity: Iterable[float],
        groups: Iterable[Sequence[int]] = (),
        tolerance: float = ROUNDING_TOLERANCE,
    ) -> JointRateLimit:
        """From any sequence of caps (a numpy array) and groups of indices."""
        return cls(
            tuple(float(v) for v in np.asarray(max_velocity, dtype=np.float64).reshape(-1)),
            tuple(tuple(int(i) for i in g) for g in groups),
            tolerance,
        )

    @property
    def size(self) -> int:
        return self._vmax.size

    def _joints(self, what: str, values: np.ndarray) -> np.ndarray:
        """``values`` as contiguous float64, one per joint; a wrong shape is the caller's bug
        (the kernels index without bounds checks): ValueError."""
        values = np.ascontiguousarray(values, dtype=np.float64)
        if values.shape != self._vmax.shape:
            raise ValueError(f"{what} has shape {values.shape}, not ({self.size},) (one per joint)")
        return values

    def reach(self, dt: float) -> np.ndarray:
        """How far (rad) each joint may move in ``dt`` seconds (for ``dt`` <= 0: zero, or
        ``inf`` where the cap is); read-only."""
        last_dt, reach = self._reach[0]
        if dt != last_dt:
            if dt > 0:
                reach = self._vmax * dt
            else:
                reach = np.where(self._vmax == math.inf, math.inf, 0.0)
            reach.setflags(write=False)
            self._reach[0] = (dt, reach)
        return reach

    def exceeds(self, step: np.ndarray, dt: float) -> np.ndarray:
        """Per joint: ``step`` (target - previous) is beyond reach in ``dt``, past the
        tolerance (each joint on its own; False for a non-finite step)."""
        out = np.empty(self.size, dtype=np.bool_)
        step = self._joints("step", step)
        _beyond(step, self.reach(dt), 1.0 + self.tolerance, out)
        return out

    def clamp(self, previous: np.ndarray, target: np.ndarray, dt: float) -> RateLimited:
        """``target`` limited to what each joint reaches from ``previous`` in ``dt`` (see the
        module's contract); never raises on a non-finite target."""
        previous = self._joints("previous", previous)
        target = self._joints("target", target)
        n = self.size
        out = np.empty(n)
        limited = np.empty(n, dtype=np.bool_)
        non_finite = np.empty(n, dtype=np.bool_)
        reach = self.reach(dt)
        _clamp_joints(previous, target, reach, 1.0 + self.tolerance, out, limited, non_finite)
        for g in self._groups:  # a group's joints move together
            if not limited[g].any():
                continue
            s = np.where(non_finite[g], 0.0, target[g] - previous[g])
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = float(np.max(np.where(s == 0.0, 0.0, np.abs(s) / reach[g])))
            out[g] = previous[g] + s / ratio  # the largest step at its reach
            limited[g] = s != 0.0
        return RateLimited(out, limited, non_finite)
