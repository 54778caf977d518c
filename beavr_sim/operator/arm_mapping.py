"""Relative motion mapping from the operator's hand to the robot's hand (BEAVR's arm mapping).

At an anchor instant (teleop start, every resume, every reset) the operator's palm pose
``H_hand_init`` and the robot hand pose ``H_robot_init`` are stored. Afterwards

    H_rel    = H_hand_init^-1 @ H_hand                    (motion in the initial palm frame)
    H_target = H_robot_init @ conj(H_rel)
    conj([[R, t], [0, 1]]) = [[A_rot @ R @ A_rot^T, s * A_trans @ t], [0, 1]]

with ``s`` the resolution scale (1.0 high, 0.6 low) and the axis matrices ``A_rot``,
``A_trans`` (the paper's ``H_RV^-1`` and ``H_TV^-1``) mapping palm-frame axes to robot-hand
axes. They are data, one :class:`AxisMap` per (embodiment, side). Our palm frame is defined
with the robot hand's axis convention (``beavr_sim.wire.hand``: +z along the fingers, +x the
palmar normal), so for the xArm7 + LEAP rigs and the RX-1 (LEAP hands too) both matrices are the identity; the Quest app's
raw Unity frame would need the paper's matrices instead.

Because nothing depends on absolute positions, the robot never jumps at an anchor: at that
instant ``H_rel`` is the identity and ``H_target == H_robot_init``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.operator import kernels
from beavr_sim.robots.embodiment import embodiment_layout
from beavr_sim.robots.robot_file import is_robot_file

RESOLUTION_SCALE = {"high": 1.0, "low": 0.6}


def _check_rotation(name: str, R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9):
        raise ValueError(f"{name} must be a 3x3 rotation matrix, got {R!r}")
    if np.linalg.det(R) < 0:
        raise ValueError(f"{name} must be a proper rotation (det +1), got det {np.linalg.det(R)}")
    return R


@dataclass(frozen=True)
class AxisMap:
    """Palm-frame axes -> robot-hand axes, for rotations and for translations."""

    A_rot: np.ndarray = field(default_factory=lambda: np.eye(3))
    A_trans: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "A_rot", _check_rotation("A_rot", self.A_rot))
        object.__setattr__(self, "A_trans", _check_rotation("A_trans", self.A_trans))


#: (embodiment, side) -> axis map. Identity for the xArm7 + LEAP rigs (see the module docstring).
AXIS_MAPS: dict[tuple[str, str], AxisMap] = {
    ("xarm7_leap_right", "right"): AxisMap(),
    ("xarm7_leap_left", "left"): AxisMap(),
    ("xarm7_leap_bimanual", "right"): AxisMap(),
    ("xarm7_leap_bimanual", "left"): AxisMap(),
    # The RX-1's hands are LEAP hands in the same hand frame convention: identity too.
    ("rx1", "right"): AxisMap(),
    ("rx1", "left"): AxisMap(),
}


def axis_map(embodiment: str, side: str) -> AxisMap:
    """The axis map of ``embodiment``'s ``side``; a robot file's (LEAP hands, the same hand
    frame convention) is its layout's (:func:`~beavr_sim.robots.embodiment.embodiment_layout`)."""
    key = (embodiment, side)
    if key not in AXIS_MAPS and is_robot_file(embodiment):
        key = (embodiment_layout(embodiment) or embodiment, side)
    if key not in AXIS_MAPS:
        valid = [f"{e}/{s}" for e, s in AXIS_MAPS]
        check_name("embodiment/side with an arm axis map", f"{embodiment}/{side}", valid)
    return AXIS_MAPS[key]


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


class RelativeMotionMapping:
    """The anchored hand -> robot mapping of one effector."""

    def __init__(self, axes: AxisMap):
        self.axes = axes
        self.T_anchor_hand: np.ndarray | None = None
        self.T_anchor_robot: np.ndarray | None = None

    @property
    def anchored(self) -> bool:
        return self.T_anchor_hand is not None

    def anchor(self, T_world_hand: np.ndarray, T_world_robot: np.ndarray) -> None:
        """Store the palm pose and the robot hand pose that correspond from now on."""
        self.T_anchor_hand = np.array(T_world_hand, dtype=np.float64)
        self.T_anchor_robot = np.array(T_world_robot, dtype=np.float64)
        # robot_target's products that depend only on the anchor, computed once here:
        # R_target = R_ar A_r R_ah^T R A_r^T, p_target = p_ar + s R_ar A_t R_ah^T (p - p_ah).
        R_ar, R_ah_T = self.T_anchor_robot[:3, :3], self.T_anchor_hand[:3, :3].T
        self._R_left = R_ar @ self.axes.A_rot @ R_ah_T
        self._R_right = np.ascontiguousarray(self.axes.A_rot.T)
        self._P = R_ar @ self.axes.A_trans @ R_ah_T
        self._p_anchor_robot = self.T_anchor_robot[:3, 3].copy()
        self._p_anchor_hand = self.T_anchor_hand[:3, 3].copy()

    def release(self) -> None:
        self.T_anchor_hand = self.T_anchor_robot = None

    def _scale(self, resolution: str) -> float:
        if self.T_anchor_hand is None or self.T_anchor_robot is None:
            raise RuntimeError("mapping not anchored: call anchor() first")
        return RESOLUTION_SCALE[check_name("resolution", resolution, RESOLUTION_SCALE)]

    def robot_target(self, T_world_hand: np.ndarray, resolution: str = "high") -> np.ndarray:
        """``T_world_robot`` target for palm pose ``T_world_hand``."""
        s = self._scale(resolution)
        # T_anchor_robot @ conj(inv(T_anchor_hand) @ T_world_hand), with the anchor's part
        # of the products precomputed in anchor().
        T_world_robot = np.empty((4, 4))
        kernels.mapped_pose(
            self._R_left, self._R_right, self._P, self._p_anchor_robot, self._p_anchor_hand,
            s, np.asarray(T_world_hand, dtype=np.float64), T_world_robot,
        )  # fmt: skip
        return T_world_robot

    def hand_for(self, T_world_robot: np.ndarray, resolution: str = "high") -> np.ndarray:
        """The inverse: the palm pose that maps to ``T_world_robot`` (synthetic traces)."""
        s = self._scale(resolution)
        conj = _inv(self.T_anchor_robot) @ np.asarray(T_world_robot, dtype=np.float64)
        A_r, A_t = self.axes.A_rot, self.axes.A_trans
        H_rel = np.eye(4)
        H_rel[:3, :3] = A_r.T @ conj[:3, :3] @ A_r
        H_rel[:3, 3] = A_t.T @ conj[:3, 3] / s
        return self.T_anchor_hand @ H_rel
