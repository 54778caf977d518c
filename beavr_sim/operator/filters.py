"""Smoothing of the tracked hand: a moving average on keypoints, a complementary filter on poses.

Both filters are deliberately simple and documented by their constants, which the operator's
config exposes. A moving average over ``window`` frames delays the keypoints by
``(window - 1) / 2`` frames (two frames at the default window of 5: about 28 ms at the Quest's
72 Hz). The complementary pose filter moves the filtered pose a fraction ``alpha`` of the way
to each new measurement (LERP on position, SLERP on rotation): its time constant is about
``(1 - alpha) / alpha`` samples.
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.operator import kernels


class KeypointSmoother:
    """Moving average of the last ``window`` keypoint arrays (any fixed shape)."""

    def __init__(self, window: int = 3):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.window = int(window)
        self._buffer: np.ndarray | None = None  # ring buffer of the last `window` arrays
        self._count = 0

    def reset(self) -> None:
        self._count = 0

    def __call__(self, keypoints: np.ndarray) -> np.ndarray:
        keypoints = np.asarray(keypoints, dtype=np.float64)
        if self._buffer is None or (self._count == 0 and self._buffer.shape[1:] != keypoints.shape):
            self._buffer = np.empty((self.window, *keypoints.shape))
            self._rows = self._buffer.reshape(self.window, -1)  # a view
        elif self._buffer.shape[1:] != keypoints.shape:
            raise ValueError(
                f"keypoints shape changed from {self._buffer.shape[1:]} to {keypoints.shape}"
            )
        slot = self._count % self.window
        self._count += 1
        out = np.empty(keypoints.shape)
        kernels.ring_average(
            self._rows, slot, min(self._count, self.window), keypoints.ravel(), out.reshape(-1)
        )
        return out


class PoseSmoother:
    """Complementary filter on a 4x4 pose: LERP position, SLERP rotation, gain ``alpha``.

    The filtered rotation is kept as a unit quaternion, so a step converts only the new
    measurement (one ``mju_mat2Quat``) and writes the result into a preallocated pose.
    """

    def __init__(self, alpha_position: float = 0.6, alpha_rotation: float = 0.6):
        for name, a in (("alpha_position", alpha_position), ("alpha_rotation", alpha_rotation)):
            if not 0.0 < a <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {a}")
        self.alpha_position = float(alpha_position)
        self.alpha_rotation = float(alpha_rotation)
        self._T: np.ndarray | None = None
        self._q = np.empty(4)  # filtered rotation

    def reset(self, T: np.ndarray | None = None) -> None:
        self._T = None
        if T is not None:
            self._start(np.asarray(T, dtype=np.float64))

    def _start(self, T: np.ndarray) -> np.ndarray:
        self._T = T.copy()
        mujoco.mju_mat2Quat(self._q, np.ascontiguousarray(T[:3, :3]).ravel())
        return self._T.copy()

    def __call__(self, T_measured: np.ndarray) -> np.ndarray:
        T_measured = np.asarray(T_measured, dtype=np.float64)
        if self._T is None:
            return self._start(T_measured)
        # LERP on the position; SLERP: q <- q * exp(alpha * log(q^-1 q_measured)), the
        # shorter way round.
        kernels.pose_slerp(self._T, self._q, T_measured, self.alpha_position, self.alpha_rotation)
        return self._T.copy()


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, q)
    return R.reshape(3, 3)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a rotation matrix."""
    w = np.empty(3)
    mujoco.mju_quat2Vel(w, quat_from_matrix(R), 1.0)
    return w


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    mujoco.mju_quatIntegrate(q, np.asarray(w, dtype=np.float64), 1.0)
    return matrix_from_quat(q)


def slerp(R_a: np.ndarray, R_b: np.ndarray, s: float) -> np.ndarray:
    """Rotation a fraction ``s`` of the way from ``R_a`` to ``R_b`` along the geodesic."""
    q_a, q_b = quat_from_matrix(R_a), quat_from_matrix(R_b)
    q_a_inv, q_rel, w = np.empty(4), np.empty(4), np.empty(3)
    mujoco.mju_negQuat(q_a_inv, q_a)
    mujoco.mju_mulQuat(q_rel, q_a_inv, q_b)
    mujoco.mju_quat2Vel(w, q_rel, 1.0)  # the shorter way round: angle in [0, pi]
    mujoco.mju_quatIntegrate(q_a, w, float(s))
    return matrix_from_quat(q_a)
