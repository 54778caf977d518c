"""Smoothing of the tracked hand, with constants in seconds: a One-Euro filter on the keypoints,
a first-order (LERP / SLERP) filter on the palm pose.

Both are low-passes ``y += a (x - y)`` with ``a = dt / (dt + tau)``, ``dt`` the time between
samples (the frames' source stamps) and ``tau`` a time constant in seconds. On a ramp such a
filter lags by exactly ``tau`` whatever the frame rate, so the smoothing delay does not
change with the headset's rate (a moving average over a fixed number of frames lags half its
window: 67 ms at 30 Hz, 22 ms at 90 Hz for five frames).

- :class:`KeypointFilter`: One-Euro (Casiez, Roussel and Vogel, CHI 2012) per joint: a
  cutoff of ``min_cutoff_hz`` at rest (``tau = 1 / (2 pi min_cutoff_hz)``: 33 ms at the
  default 4.8 Hz), raised by ``beta`` per m/s of the joint's speed (low-passed at
  ``d_cutoff_hz``) so fast motion lags less (27 ms at 0.5 m/s, 23 ms at 1 m/s with the
  default beta of 2). Each joint averages only its own valid (tracked, finite) samples; a
  joint invalid in the newest frame keeps its last value and is reported untracked by the
  caller.
- :class:`PoseFilter`: LERP on the position, SLERP on the rotation, with time constants
  ``tau_position_s`` and ``tau_rotation_s`` (11 ms by default).

The defaults are the delays of the former filters (a 5-frame average, then a pose gain of
0.6 per frame) at 60 Hz, the rate of the bundled traces: 33 ms and 11 ms, with the same
jitter at rest (an average over about five frames at 60 Hz). At the Quest's 72 Hz the former
ones were 28 ms and 9 ms; at 30 Hz 67 ms and 22 ms.

Repeated or out-of-order stamps count as a tiny step (:data:`MIN_DT`): such a sample barely
moves the filters, and nothing divides by zero.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from beavr_sim.operator import kernels

#: Smallest time step the filters use (s): a repeated or older stamp counts as this.
MIN_DT = 1e-4


def _check_positive(owner: str, **values: float) -> None:
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{owner}: {name} must be finite and > 0, got {value!r}")


def lowpass_gain(dt: float, tau: float) -> float:
    """Gain ``dt / (dt + tau)`` of one low-pass step after ``dt`` seconds (at least
    :data:`MIN_DT`; NaN too), time constant ``tau`` (s; 0: follow the sample)."""
    if not dt >= MIN_DT:
        dt = MIN_DT
    return dt / (dt + tau)


class KeypointFilter:
    """One-Euro filter on keypoints (n x 3, metres), per joint, over valid samples only.

    ``min_cutoff_hz``: cutoff at rest (the lag at rest is ``1 / (2 pi min_cutoff_hz)``);
    ``beta`` (s/m): cutoff added per m/s of joint speed; ``d_cutoff_hz``: cutoff of the speed
    estimate. The arithmetic is :func:`beavr_sim.operator.kernels.one_euro` (a microsecond).
    """

    def __init__(
        self, min_cutoff_hz: float = 4.8, beta: float = 2.0, d_cutoff_hz: float = 1.0
    ) -> None:
        _check_positive("KeypointFilter", min_cutoff_hz=min_cutoff_hz, d_cutoff_hz=d_cutoff_hz)
        if not (math.isfinite(beta) and beta >= 0):
            raise ValueError(f"KeypointFilter: beta must be finite and >= 0, got {beta!r}")
        self.min_cutoff_hz = float(min_cutoff_hz)
        self.beta = float(beta)
        self.d_cutoff_hz = float(d_cutoff_hz)
        self._shape: tuple[int, ...] | None = None

    @property
    def lag_at_rest_s(self) -> float:
        """The delay (s) on a slow ramp: ``1 / (2 pi min_cutoff_hz)``."""
        return 1.0 / (2.0 * math.pi * self.min_cutoff_hz)

    def reset(self) -> None:
        """Forget every joint: the next valid sample of each starts it afresh."""
        if self._shape is not None:
            self._seen[:] = False

    def _allocate(self, n: int) -> None:
        self._shape = (n, 3)
        self._state, self._raw, self._speed = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        self._t_last = np.zeros(n)
        self._seen = np.zeros(n, dtype=np.bool_)

    def __call__(self, keypoints: np.ndarray, valid: np.ndarray, t: float) -> np.ndarray:
        """Filtered keypoints after the sample ``keypoints`` at time ``t`` (s), ``valid`` the
        joints to use (bool, n). Joints not valid here: their last filtered value (NaN if
        never valid). Raises ValueError for a shape other than the first sample's (n x 3)."""
        keypoints = np.asarray(keypoints, dtype=np.float64)
        valid = np.asarray(valid, dtype=np.bool_)
        if self._shape is None and keypoints.ndim == 2 and keypoints.shape[1] == 3:
            self._allocate(keypoints.shape[0])
        if keypoints.shape != self._shape or valid.shape != self._shape[:1]:
            raise ValueError(
                f"KeypointFilter needs keypoints of shape {self._shape} and valid flags of "
                f"shape {self._shape[:1] if self._shape else None}, got {keypoints.shape} "
                f"and {valid.shape}"
            )
        out = np.empty(self._shape)
        kernels.one_euro(
            keypoints, valid, float(t), self.min_cutoff_hz, self.beta, self.d_cutoff_hz, MIN_DT,
            self._state, self._raw, self._speed, self._t_last, self._seen, out,
        )  # fmt: skip
        return out


class PoseFilter:
    """First-order filter on a 4x4 pose with time constants in seconds: the position moves
    ``dt / (dt + tau_position_s)`` of the way to each measurement (LERP), the rotation
    ``dt / (dt + tau_rotation_s)`` of the geodesic (SLERP); ``dt`` from the samples' times.

    On a ramp it lags by ``tau`` exactly, at any rate. The filtered rotation is kept as a
    unit quaternion, so a step converts only the new measurement and writes the result into
    a preallocated pose (:func:`beavr_sim.operator.kernels.pose_slerp`).
    """

    def __init__(self, tau_position_s: float = 0.011, tau_rotation_s: float = 0.011) -> None:
        for name, tau in (("tau_position_s", tau_position_s), ("tau_rotation_s", tau_rotation_s)):
            if not (math.isfinite(tau) and tau >= 0):
                raise ValueError(f"PoseFilter: {name} must be finite and >= 0 (s), got {tau!r}")
        self.tau_position_s = float(tau_position_s)
        self.tau_rotation_s = float(tau_rotation_s)
        self._T: np.ndarray | None = None
        self._q = np.empty(4)  # filtered rotation
        self._t = -math.inf

    def reset(self, T: np.ndarray | None = None, t: float = -math.inf) -> None:
        """Forget the pose, or start from ``T`` at time ``t``."""
        self._T = None
        if T is not None:
            self._start(np.asarray(T, dtype=np.float64), t)

    def _start(self, T: np.ndarray, t: float) -> np.ndarray:
        self._T = T.copy()
        self._t = t
        mujoco.mju_mat2Quat(self._q, np.ascontiguousarray(T[:3, :3]).ravel())
        return self._T.copy()

    def __call__(self, T_measured: np.ndarray, t: float) -> np.ndarray:
        """The filtered pose after the measurement ``T_measured`` at time ``t`` (s)."""
        T_measured = np.asarray(T_measured, dtype=np.float64)
        t = float(t)
        if self._T is None:
            return self._start(T_measured, t)
        dt = t - self._t
        if dt > 0:
            self._t = t
        # LERP on the position; SLERP: q <- q * exp(alpha * log(q^-1 q_measured)), the
        # shorter way round.
        kernels.pose_slerp(
            self._T,
            self._q,
            T_measured,
            lowpass_gain(dt, self.tau_position_s),
            lowpass_gain(dt, self.tau_rotation_s),
        )
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
