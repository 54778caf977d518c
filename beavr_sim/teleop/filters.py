"""Smoothing of the tracked hand: a moving average on keypoints, a complementary filter on poses.

Both filters are deliberately simple and documented by their constants, which the operator's
config exposes. A moving average over ``window`` frames delays the keypoints by
``(window - 1) / 2`` frames (two frames at the default window of 5: about 28 ms at the Quest's
72 Hz). The complementary pose filter moves the filtered pose a fraction ``alpha`` of the way
to each new measurement (LERP on position, SLERP on rotation): its time constant is about
``(1 - alpha) / alpha`` samples.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class KeypointSmoother:
    """Moving average of the last ``window`` keypoint arrays (any fixed shape)."""

    def __init__(self, window: int = 3):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.window = int(window)
        self._history: deque[np.ndarray] = deque(maxlen=self.window)

    def reset(self) -> None:
        self._history.clear()

    def __call__(self, keypoints: np.ndarray) -> np.ndarray:
        keypoints = np.asarray(keypoints, dtype=np.float64)
        if self._history and self._history[0].shape != keypoints.shape:
            raise ValueError(
                f"keypoints shape changed from {self._history[0].shape} to {keypoints.shape}"
            )
        self._history.append(keypoints)
        return np.mean(self._history, axis=0)


class PoseSmoother:
    """Complementary filter on a 4x4 pose: LERP position, SLERP rotation, gain ``alpha``."""

    def __init__(self, alpha_position: float = 0.6, alpha_rotation: float = 0.6):
        for name, a in (("alpha_position", alpha_position), ("alpha_rotation", alpha_rotation)):
            if not 0.0 < a <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {a}")
        self.alpha_position = float(alpha_position)
        self.alpha_rotation = float(alpha_rotation)
        self._T: np.ndarray | None = None

    def reset(self, T: np.ndarray | None = None) -> None:
        self._T = None if T is None else np.array(T, dtype=np.float64)

    def __call__(self, T_measured: np.ndarray) -> np.ndarray:
        T_measured = np.asarray(T_measured, dtype=np.float64)
        if self._T is None:
            self._T = T_measured.copy()
            return self._T.copy()
        T = np.eye(4)
        T[:3, 3] = self._T[:3, 3] + self.alpha_position * (T_measured[:3, 3] - self._T[:3, 3])
        T[:3, :3] = slerp(self._T[:3, :3], T_measured[:3, :3], self.alpha_rotation)
        self._T = T
        return T.copy()


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle) of a rotation matrix, accurate up to and near pi."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin2 = np.linalg.norm(w)  # 2 sin(angle)
    angle = float(np.arctan2(sin2, np.trace(R) - 1.0))
    if angle < 1e-7:
        return 0.5 * w
    if angle < np.pi - 1e-3:
        return w / sin2 * angle
    # Near pi the skew part vanishes: the axis is the dominant column of (R + I) / 2,
    # signed to agree with the skew part.
    M = (R + np.eye(3)) / 2.0
    k = int(np.argmax(np.diag(M)))
    axis = M[:, k] / np.sqrt(max(M[k, k], 1e-300))
    axis /= np.linalg.norm(axis)
    if np.dot(axis, w) < 0:
        axis = -axis
    return axis * angle


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = np.asarray(w, dtype=np.float64) / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def slerp(R_a: np.ndarray, R_b: np.ndarray, s: float) -> np.ndarray:
    """Rotation a fraction ``s`` of the way from ``R_a`` to ``R_b`` along the geodesic."""
    return R_a @ so3_exp(s * so3_log(R_a.T @ R_b))
