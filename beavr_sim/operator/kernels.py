"""Compiled per-tick kernels of the operator's QPs (numba).

The operator's control tick assembles two small QPs (arm IK, LEAP retargeting) from MuJoCo's
kinematics: point Jacobians, collision rows, Hessian, gradient and bounds. Written as numpy
expressions this is a hundred or so calls on arrays of 3 to 50 numbers, each costing a few
microseconds of interpreter and dispatch overhead: most of the tick. Here the same
arithmetic is written as plain loops and compiled once by numba (cached on disk next to
this module, so later processes load it in milliseconds), one call per piece.

The formulas are those of :mod:`beavr_sim.operator.jacobians` (point Jacobians from the dofs'
motion subspaces ``cdof``) and of mink's tasks and limits; the callers document them, and
the tests check the kernels against ``mj_jac``, finite differences and the numpy forms.

Inputs are float64 / int64 arrays in MuJoCo's layouts (``cdof``: nv x 6, angular then
linear; contact frames: ncon x 9 with the normal first).
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)


@_jit
def point_jacobians(cdof, subtree_com, root, chain, bodies, points, out):
    """Fill ``out`` (k, 3, nv) with the translational Jacobians of ``points`` (k, 3; world)
    fixed to ``bodies`` (k): column j is ``chain[b, j] (lin_j + ang_j x (p - c_root(b)))``."""
    nv = cdof.shape[0]
    for i in range(bodies.shape[0]):
        b = bodies[i]
        r = root[b]
        ox = points[i, 0] - subtree_com[r, 0]
        oy = points[i, 1] - subtree_com[r, 1]
        oz = points[i, 2] - subtree_com[r, 2]
        for j in range(nv):
            m = chain[b, j]
            if m == 0.0:
                out[i, 0, j] = 0.0
                out[i, 1, j] = 0.0
                out[i, 2, j] = 0.0
                continue
            ax, ay, az = cdof[j, 0], cdof[j, 1], cdof[j, 2]
            out[i, 0, j] = m * (cdof[j, 3] + ay * oz - az * oy)
            out[i, 1, j] = m * (cdof[j, 4] + az * ox - ax * oz)
            out[i, 2, j] = m * (cdof[j, 5] + ax * oy - ay * ox)
    return out


@_jit
def _normal_term(cdof, subtree_com, root, chain, b, px, py, pz, nx, ny, nz, sign, row):
    """``row += sign * n^T J(p)`` for point p fixed to body b (n . (ang x o) = ang . (o x n))."""
    r = root[b]
    ox = px - subtree_com[r, 0]
    oy = py - subtree_com[r, 1]
    oz = pz - subtree_com[r, 2]
    cx = oy * nz - oz * ny
    cy = oz * nx - ox * nz
    cz = ox * ny - oy * nx
    for j in range(cdof.shape[0]):
        m = chain[b, j]
        if m != 0.0:
            row[j] += (
                sign
                * m
                * (
                    cdof[j, 0] * cx
                    + cdof[j, 1] * cy
                    + cdof[j, 2] * cz
                    + cdof[j, 3] * nx
                    + cdof[j, 4] * ny
                    + cdof[j, 5] * nz
                )
            )


@_jit
def normal_rows(cdof, subtree_com, root, chain, normals, bodies1, points1, bodies2, points2):
    """(k, nv) rows ``n^T (J(p1) - J(p2))`` (see ``PointJacobians.normal_rows``)."""
    k = normals.shape[0]
    rows = np.zeros((k, cdof.shape[0]))
    for i in range(k):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        _normal_term(
            cdof, subtree_com, root, chain, bodies1[i],
            points1[i, 0], points1[i, 1], points1[i, 2], nx, ny, nz, 1.0, rows[i],
        )  # fmt: skip
        _normal_term(
            cdof, subtree_com, root, chain, bodies2[i],
            points2[i, 0], points2[i, 1], points2[i, 2], nx, ny, nz, -1.0, rows[i],
        )  # fmt: skip
    return rows


@_jit
def select_contacts(geom, dist, lookup, npairs, closest_only):
    """Indices of the contacts to keep and their pair indices (``lookup[g1, g2]``).

    ``closest_only``: each pair's closest contact (the first of equally close ones), in pair
    order; otherwise every contact, in MuJoCo's order."""
    n = geom.shape[0]
    if not closest_only or n <= 1:
        pairs = np.empty(n, dtype=np.int64)
        for i in range(n):
            pairs[i] = lookup[geom[i, 0], geom[i, 1]]
        return np.arange(n), pairs
    best = np.full(npairs, -1, dtype=np.int64)
    for i in range(n):
        p = lookup[geom[i, 0], geom[i, 1]]
        if best[p] < 0 or dist[i] < dist[best[p]]:
            best[p] = i
    k = 0
    for p in range(npairs):
        if best[p] >= 0:
            k += 1
    keep = np.empty(k, dtype=np.int64)
    pairs = np.empty(k, dtype=np.int64)
    k = 0
    for p in range(npairs):
        if best[p] >= 0:
            keep[k] = best[p]
            pairs[k] = p
            k += 1
    return keep, pairs


@_jit
def contact_rows(
    geom, dist, frame, pos, lookup, geom_body, npairs, closest_only,
    cdof, subtree_com, root, chain, gain, min_distance, relaxation, dt, pairs, dists, rows, h,
    recovery=0.0,
):  # fmt: skip
    """mink's collision-avoidance rows from MuJoCo's contacts, ``G dq <= h``: per kept contact
    (distance d, normal n from geom 1 to geom 2, midpoint p; witness points ``p -/+ d n / 2``)
    the row ``n^T (J(p1) - J(p2))`` and ``h = gain (d - min_distance) / dt`` ``+ relaxation``.
    Once within ``min_distance``, ``h = -recovery (min_distance - d) / dt`` instead: mink's
    choice (``recovery`` 0) only forbids going deeper, so a pair that linearisation errors let
    inside stays there; ``recovery`` > 0 undoes that fraction of the intrusion per step. Writes the first k entries of ``pairs`` (pair
    indices), ``dists``, ``rows`` and ``h`` (capacity: at least one per contact) and returns
    k, or -1 (nothing written) when they are too short."""
    keep, kept_pairs = select_contacts(geom, dist, lookup, npairs, closest_only)
    k = keep.shape[0]
    if k > rows.shape[0] or k > h.shape[0] or k > pairs.shape[0] or k > dists.shape[0]:
        return -1
    rows[:k] = 0.0
    for r in range(k):
        i = keep[r]
        d = dist[i]
        nx, ny, nz = frame[i, 0], frame[i, 1], frame[i, 2]
        hx, hy, hz = 0.5 * d * nx, 0.5 * d * ny, 0.5 * d * nz
        px, py, pz = pos[i, 0], pos[i, 1], pos[i, 2]
        b1, b2 = geom_body[geom[i, 0]], geom_body[geom[i, 1]]
        _normal_term(
            cdof, subtree_com, root, chain, b1, px - hx, py - hy, pz - hz, nx, ny, nz, 1.0, rows[r]
        )
        _normal_term(
            cdof, subtree_com, root, chain, b2, px + hx, py + hy, pz + hz, nx, ny, nz, -1.0, rows[r]
        )
        if d > min_distance:
            h[r] = gain * (d - min_distance) / dt + relaxation
        else:
            h[r] = -recovery * (min_distance - d) / dt + relaxation
        dists[r] = d
        pairs[r] = kept_pairs[r]
    return k


@_jit
def points_qp(
    cdof, subtree_com, root, chain, bodies, positions, targets, cost,
    qpos, posture, posture_weight, diagonal, lower_q, upper_q, limit_gain, max_step, held,
    H, c, lower, upper,
):  # fmt: skip
    """The retargeting step's QP in the step ``dq``: minimise ``1/2 dq^T H dq + c^T dq``
    under ``lower <= dq <= upper``, for the weighted point residuals ``cost * (p - target)``
    (3 rows per point), ``posture_weight * (q - posture)`` and ``diagonal`` on H's diagonal.
    Bounds: ``limit_gain`` of the way to each joint limit, at most ``max_step``; 0 for
    ``held`` dofs. Writes H (nv x nv), c, lower and upper (nv)."""
    nv = cdof.shape[0]
    k = bodies.shape[0]
    J = np.empty((k, 3, nv))
    point_jacobians(cdof, subtree_com, root, chain, bodies, positions, J)
    H[:] = 0.0
    c[:] = 0.0
    for i in range(k):
        for a in range(3):
            w = cost[3 * i + a]
            if w == 0.0:
                continue
            w2 = w * w
            e = positions[i, a] - targets[i, a]
            for j in range(nv):
                Jj = J[i, a, j]
                if Jj == 0.0:
                    continue
                c[j] += w2 * e * Jj
                for m in range(j, nv):
                    H[j, m] += w2 * Jj * J[i, a, m]
    for j in range(nv):
        H[j, j] += diagonal
        for m in range(j + 1, nv):
            H[m, j] = H[j, m]
        c[j] += posture_weight * (qpos[j] - posture[j])
        if held[j]:
            lower[j] = 0.0
            upper[j] = 0.0
        else:
            upper[j] = min(limit_gain * (upper_q[j] - qpos[j]), max_step)
            lower[j] = max(limit_gain * (lower_q[j] - qpos[j]), -max_step)


@_jit
def stack_bounds(lower, upper, h, bupper, blower, sense):
    """DAQP's bounds for simple bounds ``lower <= x <= upper`` then rows ``A x <= h``, in the
    first ``m = n + k`` entries of ``bupper``, ``blower`` (-1e30: none) and ``sense`` (0:
    inequality). Returns m, or -1 (nothing written) when they are too short."""
    n, k = lower.shape[0], h.shape[0]
    m = n + k
    if m > bupper.shape[0] or m > blower.shape[0] or m > sense.shape[0]:
        return -1
    for j in range(n):
        bupper[j] = upper[j]
        blower[j] = lower[j]
        sense[j] = 0
    for j in range(k):
        bupper[n + j] = h[j]
        blower[n + j] = -1e30
        sense[n + j] = 0
    return m


@_jit
def quat_from_matrix(R):
    """Unit quaternion (w, x, y, z), w >= 0, of the rotation matrix ``R`` (3 x 3), by
    Shepperd's method (the largest of w, x, y, z computed first, for accuracy)."""
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t >= max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2.0 * np.sqrt(1.0 + t)
        w = 0.25 * s
        x = (R[2, 1] - R[1, 2]) / s
        y = (R[0, 2] - R[2, 0]) / s
        z = (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w = (R[2, 1] - R[1, 2]) / s
        x = 0.25 * s
        y = (R[0, 1] + R[1, 0]) / s
        z = (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w = (R[0, 2] - R[2, 0]) / s
        x = (R[0, 1] + R[1, 0]) / s
        y = 0.25 * s
        z = (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w = (R[1, 0] - R[0, 1]) / s
        x = (R[0, 2] + R[2, 0]) / s
        y = (R[1, 2] + R[2, 1]) / s
        z = 0.25 * s
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = np.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


@_jit
def _log_quat(w, x, y, z):
    """Rotation vector of the unit quaternion (w, x, y, z), the shorter way round."""
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    sin_half = np.sqrt(x * x + y * y + z * z)
    if sin_half < 1e-12:
        return 2.0 * x, 2.0 * y, 2.0 * z
    scale = 2.0 * np.arctan2(sin_half, w) / sin_half
    return scale * x, scale * y, scale * z


@_jit
def rotation_vector(R):
    """Rotation vector (axis * angle, angle in [0, pi]) of the rotation matrix ``R``."""
    w, x, y, z = quat_from_matrix(R)
    out = np.empty(3)
    out[0], out[1], out[2] = _log_quat(w, x, y, z)
    return out


@_jit
def _quat_mul(aw, ax, ay, az, bw, bx, by, bz):
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@_jit
def pose_slerp(T, q, T_measured, alpha_position, alpha_rotation):
    """One step of the complementary pose filter, in place: ``T``'s position moves
    ``alpha_position`` of the way to ``T_measured``'s (LERP), its rotation ``q`` (unit
    quaternion, w first) ``alpha_rotation`` of the geodesic to the measured one (SLERP, the
    shorter way round): ``q <- q exp(alpha log(q^-1 q_measured))``; ``T``'s rotation block
    is set from the new ``q``."""
    for a in range(3):
        T[a, 3] += alpha_position * (T_measured[a, 3] - T[a, 3])
    mw, mx, my, mz = quat_from_matrix(T_measured[:3, :3])
    rw, rx, ry, rz = _quat_mul(q[0], -q[1], -q[2], -q[3], mw, mx, my, mz)
    vx, vy, vz = _log_quat(rw, rx, ry, rz)
    angle = alpha_rotation * np.sqrt(vx * vx + vy * vy + vz * vz)
    if angle > 0.0:
        s = np.sin(0.5 * angle) / np.sqrt(vx * vx + vy * vy + vz * vz)
        w, x, y, z = _quat_mul(q[0], q[1], q[2], q[3], np.cos(0.5 * angle), s * vx, s * vy, s * vz)
        n = np.sqrt(w * w + x * x + y * y + z * z)
        q[0], q[1], q[2], q[3] = w / n, x / n, y / n, z / n
    w, x, y, z = q[0], q[1], q[2], q[3]
    T[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    T[0, 1] = 2.0 * (x * y - w * z)
    T[0, 2] = 2.0 * (x * z + w * y)
    T[1, 0] = 2.0 * (x * y + w * z)
    T[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    T[1, 2] = 2.0 * (y * z - w * x)
    T[2, 0] = 2.0 * (x * z - w * y)
    T[2, 1] = 2.0 * (y * z + w * x)
    T[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@_jit
def arm_qp(
    jac, dofs, weights, T_world_target, p_world_hand, R_world_hand, qpos, qpos_adr,
    posture, posture_weight, damping, lm_damping, max_step, lower_q, upper_q, limit_gain,
    H, c, lower, upper,
):  # fmt: skip
    """The arm IK step's QP in the arm joints' step ``dq`` (``ArmIK._step`` documents it):
    weighted hand pose error ``e = weights * (p_target - p_hand, log(R_target R_hand^T))``,
    ``J = weights * jac[:, dofs]``, ``H = J^T J + (posture_weight + damping + lm_damping
    |e|^2) I``, ``c = -J^T e + posture_weight (q - posture)``; bounds ``limit_gain`` of the
    way to each joint limit and at most ``max_step``, but never forcing a joint that is past
    a limit further in (0 stays allowed). Writes H (n x n), c, lower and upper (n)."""
    n = dofs.shape[0]
    e = np.empty(6)
    for a in range(3):
        e[a] = weights[a] * (T_world_target[a, 3] - p_world_hand[a])
    R = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            R[a, b] = (
                T_world_target[a, 0] * R_world_hand[b, 0]
                + T_world_target[a, 1] * R_world_hand[b, 1]
                + T_world_target[a, 2] * R_world_hand[b, 2]
            )
    w = rotation_vector(R)
    for a in range(3):
        e[3 + a] = weights[3 + a] * w[a]
    J = np.empty((6, n))
    for a in range(6):
        for j in range(n):
            J[a, j] = weights[a] * jac[a, dofs[j]]
    ee = 0.0
    for a in range(6):
        ee += e[a] * e[a]
    diagonal = posture_weight + damping + lm_damping * ee
    H[:] = 0.0
    c[:] = 0.0
    for a in range(6):
        for j in range(n):
            c[j] -= e[a] * J[a, j]
            for m in range(j, n):
                H[j, m] += J[a, j] * J[a, m]
    for j in range(n):
        for m in range(j + 1, n):
            H[m, j] = H[j, m]
    for j in range(n):
        H[j, j] += diagonal
        q = qpos[qpos_adr[j]]
        c[j] += posture_weight * (q - posture[j])
        upper[j] = max(min(limit_gain * (upper_q[j] - q), max_step), 0.0)
        lower[j] = min(max(limit_gain * (lower_q[j] - q), -max_step), 0.0)


@_jit
def palm_pose(joints, wrist, middle, index, little, sign, T):
    """Fill ``T`` (4 x 4) with the palm frame of hand joints ``joints`` (n x 3): origin at
    joint ``wrist``; z from the wrist to the middle knuckle; x ``sign`` (index - little
    knuckle) x z, Gram-Schmidt orthonormalised against z; y = z x x. Returns 0, or 1 when
    wrist and middle knuckle coincide, 2 when the knuckles lie in line with the fingers
    (``T`` is then not set)."""
    zx = joints[middle, 0] - joints[wrist, 0]
    zy = joints[middle, 1] - joints[wrist, 1]
    zz = joints[middle, 2] - joints[wrist, 2]
    z_norm = np.sqrt(zx * zx + zy * zy + zz * zz)
    if z_norm < 1e-6:
        return 1
    zx, zy, zz = zx / z_norm, zy / z_norm, zz / z_norm
    ax = joints[index, 0] - joints[little, 0]
    ay = joints[index, 1] - joints[little, 1]
    az = joints[index, 2] - joints[little, 2]
    xx = sign * (ay * zz - az * zy)
    xy = sign * (az * zx - ax * zz)
    xz = sign * (ax * zy - ay * zx)
    dot = xx * zx + xy * zy + xz * zz
    xx, xy, xz = xx - dot * zx, xy - dot * zy, xz - dot * zz
    x_norm = np.sqrt(xx * xx + xy * xy + xz * xz)
    if x_norm < 1e-6:
        return 2
    xx, xy, xz = xx / x_norm, xy / x_norm, xz / x_norm
    T[0, 0], T[1, 0], T[2, 0] = xx, xy, xz
    T[0, 1], T[1, 1], T[2, 1] = zy * xz - zz * xy, zz * xx - zx * xz, zx * xy - zy * xx
    T[0, 2], T[1, 2], T[2, 2] = zx, zy, zz
    T[0, 3], T[1, 3], T[2, 3] = joints[wrist, 0], joints[wrist, 1], joints[wrist, 2]
    T[3, 0], T[3, 1], T[3, 2], T[3, 3] = 0.0, 0.0, 0.0, 1.0
    return 0


@_jit
def in_frame(points, T, out):
    """``points`` (n x 3) expressed in the frame of pose ``T``: ``(p - t) R``, into ``out``."""
    n = points.shape[0]
    for i in range(n):
        dx = points[i, 0] - T[0, 3]
        dy = points[i, 1] - T[1, 3]
        dz = points[i, 2] - T[2, 3]
        for a in range(3):
            out[i, a] = dx * T[0, a] + dy * T[1, a] + dz * T[2, a]


@_jit
def point_targets(keypoints, tracked, human_ids, scales, offset, targets, cost, base_cost):
    """The retargeting's point targets from palm-frame keypoints, in place: for point i
    (human joint ``human_ids[i]``), if tracked, ``targets[i] = offset + scales[i] *
    keypoints[human_ids[i]]`` (untracked points keep theirs); ``cost`` reset to
    ``base_cost``. Returns -1 (nothing changed) when a tracked point is NaN/inf, else 1 when
    every point is tracked, 0 when some are not."""
    k = human_ids.shape[0]
    for i in range(k):
        h = human_ids[i]
        if tracked[h]:
            for a in range(3):
                if not np.isfinite(keypoints[h, a]):
                    return -1
    all_tracked = 1
    for i in range(k):
        h = human_ids[i]
        if tracked[h]:
            for a in range(3):
                targets[i, a] = offset[a] + scales[i] * keypoints[h, a]
        else:
            all_tracked = 0
    for j in range(cost.shape[0]):
        cost[j] = base_cost[j]
    return all_tracked


@_jit
def gather_points(site_xpos, xpos, is_site, ids, out):
    """``out[i] = site_xpos[ids[i]]`` where ``is_site[i]``, else ``xpos[ids[i]]``: the world
    positions of a mix of sites and body origins."""
    for i in range(ids.shape[0]):
        src = site_xpos if is_site[i] else xpos
        for a in range(3):
            out[i, a] = src[ids[i], a]


@_jit
def gather_clip(values, index, lower, upper, out):
    """``out = min(max(values[index], lower), upper)``."""
    for i in range(index.shape[0]):
        out[i] = min(max(values[index[i]], lower[i]), upper[i])


@_jit
def mapped_pose(R_left, R_right, P, p_anchor_robot, p_anchor_hand, scale, T_world_hand, out):
    """The relative motion map's target (``RelativeMotionMapping.robot_target``): rotation
    ``R_left R R_right``, position ``p_anchor_robot + scale P (p - p_anchor_hand)``, for
    hand pose ``T_world_hand`` = (R, p), into the 4 x 4 pose ``out``."""
    M = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            M[a, b] = (
                R_left[a, 0] * T_world_hand[0, b]
                + R_left[a, 1] * T_world_hand[1, b]
                + R_left[a, 2] * T_world_hand[2, b]
            )
    for a in range(3):
        for b in range(3):
            out[a, b] = M[a, 0] * R_right[0, b] + M[a, 1] * R_right[1, b] + M[a, 2] * R_right[2, b]
    dx = T_world_hand[0, 3] - p_anchor_hand[0]
    dy = T_world_hand[1, 3] - p_anchor_hand[1]
    dz = T_world_hand[2, 3] - p_anchor_hand[2]
    for a in range(3):
        out[a, 3] = p_anchor_robot[a] + scale * (P[a, 0] * dx + P[a, 1] * dy + P[a, 2] * dz)
    out[3, 0], out[3, 1], out[3, 2], out[3, 3] = 0.0, 0.0, 0.0, 1.0


@_jit
def one_euro(x, valid, t, min_cutoff, beta, d_cutoff, min_dt, state, raw, speed, t_last, seen, out):
    """One step of the One-Euro filter (Casiez et al. 2012) on points ``x`` (n x 3) sampled
    at time ``t`` (s), per point, in place. Each point ``i`` with ``valid[i]``: ``dt`` =
    ``t - t_last[i]`` (at least ``min_dt``: repeated or out-of-order stamps count as a tiny
    step, never as zero or negative); its velocity from the previous *raw* sample (so a
    ramp's is exact at any rate) is low-passed with cutoff ``d_cutoff`` (Hz) into ``speed``
    (n x 3); the point itself with cutoff ``min_cutoff + beta |speed|`` (Hz, |.| the 3-D
    norm) into ``state``; each low-pass is ``y += a (x - y)`` with ``a = dt / (dt + tau)``,
    ``tau = 1 / (2 pi cutoff)``, whose lag on a ramp is exactly ``tau`` whatever ``dt``.
    A point's first valid sample (``seen[i]`` False) starts it. Points not valid here keep
    their state. ``out[i]``: ``state[i]`` once seen, else NaN."""
    tau_d = 1.0 / (2.0 * np.pi * d_cutoff)
    for i in range(x.shape[0]):
        if not valid[i]:
            for a in range(3):
                out[i, a] = state[i, a] if seen[i] else np.nan
            continue
        if not seen[i]:
            for a in range(3):
                state[i, a] = raw[i, a] = out[i, a] = x[i, a]
                speed[i, a] = 0.0
            t_last[i] = t
            seen[i] = True
            continue
        dt = t - t_last[i]
        if not dt >= min_dt:  # NaN-safe
            dt = min_dt
        else:
            t_last[i] = t
        a_d = dt / (dt + tau_d)
        s2 = 0.0
        for a in range(3):
            speed[i, a] += a_d * ((x[i, a] - raw[i, a]) / dt - speed[i, a])
            s2 += speed[i, a] * speed[i, a]
        tau = 1.0 / (2.0 * np.pi * (min_cutoff + beta * np.sqrt(s2)))
        alpha = dt / (dt + tau)
        for a in range(3):
            state[i, a] += alpha * (x[i, a] - state[i, a])
            raw[i, a] = x[i, a]
            out[i, a] = state[i, a]


@_jit
def valid_joints(joints, tracked, required, valid):
    """``valid[i] = tracked[i]`` and joint ``i`` (of ``joints``, n x 3) finite, in place.
    Returns (how many joints are flagged tracked but not finite, whether every joint of
    ``required`` is valid)."""
    bad = 0
    for i in range(joints.shape[0]):
        ok = tracked[i]
        if ok:
            for a in range(3):
                if not np.isfinite(joints[i, a]):
                    ok = False
            if not ok:
                bad += 1
        valid[i] = ok
    complete = True
    for i in required:
        if not valid[i]:
            complete = False
    return bad, complete
