"""The palm frame of a tracked hand (convention: :mod:`beavr_sim.wire.hand`).

Origin at the wrist, +z from the wrist towards the middle knuckle, +x the palmar normal,
y = z x x; built from the wrist and the index, middle and little knuckles and Gram-Schmidt
orthonormalised (the arithmetic in :func:`beavr_sim.operator.kernels.palm_pose`).
"""

from __future__ import annotations

import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.operator import kernels
from beavr_sim.wire.hand import JOINT_INDEX, PALMAR_NORMAL_SIGN, SIDES

_WRIST, _MIDDLE_KNUCKLE = JOINT_INDEX["wrist"], JOINT_INDEX["middle_proximal"]
_INDEX_KNUCKLE, _LITTLE_KNUCKLE = JOINT_INDEX["index_proximal"], JOINT_INDEX["little_proximal"]

_PALM_ERRORS = {
    1: "degenerate hand: wrist and middle knuckle coincide",
    2: "degenerate hand: knuckles in line with the fingers",
}


def T_world_palm(joints: np.ndarray, side: str) -> np.ndarray:
    """4x4 pose of the palm frame (origin at the wrist) in the frame of ``joints``."""
    sign = PALMAR_NORMAL_SIGN.get(side)
    if sign is None:
        check_name("side", side, SIDES)
    joints = np.asarray(joints, dtype=np.float64)
    T = np.empty((4, 4))
    status = kernels.palm_pose(
        joints, _WRIST, _MIDDLE_KNUCKLE, _INDEX_KNUCKLE, _LITTLE_KNUCKLE, sign, T
    )
    if status:
        raise ValueError(_PALM_ERRORS[status])
    return T


def R_world_palm(joints: np.ndarray, side: str) -> np.ndarray:
    """Rotation of the palm frame from the 26 canonical joints."""
    return T_world_palm(joints, side)[:3, :3].copy()


def keypoints_in_palm(joints: np.ndarray, side: str) -> np.ndarray:
    """The 26 joints expressed in the palm frame (26 x 3)."""
    joints = np.asarray(joints, dtype=np.float64)
    out = np.empty(joints.shape)
    kernels.in_frame(joints, T_world_palm(joints, side), out)
    return out
