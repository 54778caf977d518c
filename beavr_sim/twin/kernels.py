"""The guard's per-tick arithmetic, compiled by numba (cached on disk).

The guard runs on every command, before the twin and any hardware: numpy on arrays of 20-50
numbers is mostly call overhead (about 70 us for the geom boxes, 30 us for the joint rules),
these loops take a few. :class:`~beavr_sim.twin.guard.CollisionGuard` owns the state and
calls these; ``tests/test_extents.py`` and ``tests/test_guard.py`` check them.
"""

from __future__ import annotations

import math

import mujoco
import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)

SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)
BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
ELLIPSOID = int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)

#: Joint rule codes of :func:`joint_rules` (0: fine).
NON_FINITE, LIMIT, VELOCITY, ACCELERATION = 1, 2, 3, 4


@_jit
def geom_boxes(xpos, xmat, geoms, types, size, aabb, centre, half):
    """World axis-aligned boxes of ``geoms`` (exact for primitives; other types: the world box
    of their local ``aabb``) into ``centre`` and ``half`` (n x 3). ``xmat`` rows are MuJoCo's
    row-major 3x3 rotations, R[i, j] = xmat[g, 3 i + j]."""
    for k in range(geoms.shape[0]):
        g = geoms[k]
        t = types[k]
        s0, s1, s2 = size[k, 0], size[k, 1], size[k, 2]
        for i in range(3):
            r0, r1, r2 = xmat[g, 3 * i], xmat[g, 3 * i + 1], xmat[g, 3 * i + 2]
            centre[k, i] = xpos[g, i]
            if t == SPHERE:
                half[k, i] = s0
            elif t == CAPSULE:
                half[k, i] = abs(r2) * s1 + s0
            elif t == CYLINDER:
                half[k, i] = abs(r2) * s1 + s0 * math.sqrt(max(0.0, 1.0 - r2 * r2))
            elif t == BOX:
                half[k, i] = abs(r0) * s0 + abs(r1) * s1 + abs(r2) * s2
            elif t == ELLIPSOID:
                half[k, i] = math.sqrt((r0 * s0) ** 2 + (r1 * s1) ** 2 + (r2 * s2) ** 2)
            else:
                centre[k, i] += r0 * aabb[k, 0] + r1 * aabb[k, 1] + r2 * aabb[k, 2]
                half[k, i] = abs(r0) * aabb[k, 3] + abs(r1) * aabb[k, 4] + abs(r2) * aabb[k, 5]


@_jit
def outside(centre, half, lower, upper, flags):
    """``flags[k]``: geom k's box leaves [lower, upper] (per geom, n x 3); returns how many."""
    count = 0
    for k in range(centre.shape[0]):
        out = False
        for i in range(3):
            if centre[k, i] - half[k, i] < lower[k, i] or centre[k, i] + half[k, i] > upper[k, i]:
                out = True
        flags[k] = out
        count += out
    return count


@_jit
def joint_rules(action, previous, has_previous, fast, velocity, lower, upper, amax, dt, codes):
    """Per joint the first rule ``action`` breaks (``codes``: 0 or a rule code); returns how many
    joints break one. Speed and acceleration need ``has_previous`` and ``dt > 0``; ``fast``:
    the joints whose step from ``previous`` the rate limit marks as beyond reach
    (:meth:`~beavr_sim.twin.rate_limit.JointRateLimit.exceeds`); ``velocity`` is that of the
    last accepted command."""
    count = 0
    tol = 1.0 + 1e-9
    for i in range(action.shape[0]):
        q = action[i]
        code = 0
        if not math.isfinite(q):
            code = NON_FINITE
        elif q < lower[i] or q > upper[i]:
            code = LIMIT
        elif has_previous and dt > 0.0:
            v = (q - previous[i]) / dt
            if fast[i]:
                code = VELOCITY
            elif abs(v - velocity[i]) > amax[i] * dt * tol:
                code = ACCELERATION
        codes[i] = code
        count += code != 0
    return count


@_jit
def set_robot_qpos(qpos, qpos_now, adr, action):
    """``qpos`` = ``qpos_now`` with the robot's joints (addresses ``adr``) at ``action``."""
    qpos[:] = qpos_now
    for i in range(adr.shape[0]):
        qpos[adr[i]] = action[i]


@_jit
def gather_rows(values, rows, out):
    """``out[k] = values[rows[k]]`` (the moving geoms' centres)."""
    for k in range(rows.shape[0]):
        for i in range(values.shape[1]):
            out[k, i] = values[rows[k], i]


@_jit
def largest_move(a, b):
    """The largest distance between matching rows of ``a`` and ``b`` (n x 3)."""
    best = 0.0
    for k in range(a.shape[0]):
        d = (a[k, 0] - b[k, 0]) ** 2 + (a[k, 1] - b[k, 1]) ** 2 + (a[k, 2] - b[k, 2]) ** 2
        best = max(best, d)
    return math.sqrt(best)


@_jit
def same(a, b):
    """``a`` and ``b`` (same shape) hold the same numbers."""
    for i in range(a.shape[0]):
        if a[i] != b[i]:
            return False
    return True


@_jit
def lerp(a, b, s, out):
    for i in range(a.shape[0]):
        out[i] = a[i] + s * (b[i] - a[i])


def warm_up() -> None:
    """Compile (or load from the cache) every kernel once."""
    x = np.zeros((1, 3))
    geom_boxes(
        x, np.eye(3).reshape(1, 9), np.zeros(1, np.int64), np.zeros(1, np.int64),
        np.ones((1, 3)), np.zeros((1, 6)), np.zeros((1, 3)), np.zeros((1, 3)),
    )  # fmt: skip
    outside(x, x, x, x + 1.0, np.zeros(1, np.bool_))
    v = np.zeros(1)
    joint_rules(
        v, v, True, np.zeros(1, np.bool_), v, v - 1, v + 1, v + 1, 0.1, np.zeros(1, np.int64)
    )
    adr = np.zeros(1, np.int64)
    set_robot_qpos(v.copy(), v, adr, v)
    gather_rows(x, adr, x.copy())
    largest_move(x, x)
    same(v, v)
    lerp(v, v, 0.5, v.copy())
