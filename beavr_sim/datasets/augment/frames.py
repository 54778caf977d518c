"""Reference frames of the scene's things and the rigid moves between two scenes.

A thing (free object or fixture) has a pose; its *yaw symmetry* is the turn about the world
z axis that leaves its footprint unchanged (``0``: any turn, a cylinder or sphere; ``pi / 2``:
a square box; ``pi``: a rectangle; ``2 pi``: none known). Carrying a palm trajectory from a
source scene into a new one uses T_world_new * inv(T_world_src) of its reference thing,
restricted to a translation and a turn about z, the turn reduced by the symmetry (a tin
turned in the new scene is grasped as in the source, not from behind).

Bridging: :func:`blend` moves from a pose under one transform to the pose under the next
(position linear, orientation slerp) with a smoothstep weight.
"""

from __future__ import annotations

import mujoco
import numpy as np

FULL_TURN = 2 * np.pi


def yaw_of(R: np.ndarray) -> float:
    """The heading (rad) of a rotation matrix's x axis in the world xy plane."""
    return float(np.arctan2(R[1, 0], R[0, 0]))


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def body_yaw_symmetry(model: mujoco.MjModel, geom_ids: np.ndarray) -> float:
    """The yaw symmetry of a body made of ``geom_ids`` (see the module docstring): only a
    body of one geom centred on its origin is known to be symmetric."""
    if len(geom_ids) != 1:
        return FULL_TURN
    g = int(geom_ids[0])
    if np.linalg.norm(model.geom_pos[g][:2]) > 1e-6:
        return FULL_TURN
    kind, size = int(model.geom_type[g]), model.geom_size[g]
    round_kinds = (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_SPHERE,
                   mujoco.mjtGeom.mjGEOM_CAPSULE)  # fmt: skip
    if kind in tuple(int(k) for k in round_kinds):
        return 0.0
    if kind == int(mujoco.mjtGeom.mjGEOM_BOX):
        return np.pi / 2 if abs(size[0] - size[1]) < 1e-6 else np.pi
    return FULL_TURN


def carry(
    src_pos: np.ndarray, src_yaw: float, new_pos: np.ndarray, new_yaw: float, symmetry: float
) -> np.ndarray:
    """The 4x4 world transform taking the source thing's frame onto the new one's (a turn
    about z, reduced by ``symmetry``, and a translation)."""
    turn = 0.0
    if symmetry > 0:
        turn = float((new_yaw - src_yaw + symmetry / 2) % symmetry - symmetry / 2)
    T = np.eye(4)
    T[:3, :3] = rot_z(turn)
    T[:3, 3] = np.asarray(new_pos, float) - T[:3, :3] @ np.asarray(src_pos, float)
    return T


def smoothstep(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


def blend(A: np.ndarray, B: np.ndarray, s: float) -> np.ndarray:
    """The pose ``s`` of the way from 4x4 pose ``A`` to ``B`` (0: A, 1: B)."""
    if s <= 0.0:
        return A.copy()
    if s >= 1.0:
        return B.copy()
    qa, qb, q = np.zeros(4), np.zeros(4), np.zeros(4)
    mujoco.mju_mat2Quat(qa, A[:3, :3].reshape(-1))
    mujoco.mju_mat2Quat(qb, B[:3, :3].reshape(-1))
    if np.dot(qa, qb) < 0:
        qb = -qb
    # slerp
    dot = float(np.clip(np.dot(qa, qb), -1.0, 1.0))
    theta = np.arccos(dot)
    if theta < 1e-6:
        q = qa
    else:
        q = (np.sin((1 - s) * theta) * qa + np.sin(s * theta) * qb) / np.sin(theta)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, q / np.linalg.norm(q))
    T = np.eye(4)
    T[:3, :3] = mat.reshape(3, 3)
    T[:3, 3] = (1 - s) * A[:3, 3] + s * B[:3, 3]
    return T
