"""Twin cameras placed at real cameras' poses and fields of view.

A :class:`PlacedCamera` is a camera's pose in the world frame, ``T_world_camera`` (4x4, the
camera frame being OpenCV's optical frame: x right, y down, z forward, as calibration and ROS
give it), and either its intrinsics (fx, fy, cx, cy in pixels at width x height, OpenCV's
convention: pixel centres at integer coordinates) or a vertical field of view.
:func:`place_camera` puts it into a scene spec as a MuJoCo camera of its name (moving a
fixed camera of that name, e.g. ``front``, or adding a new one). MuJoCo cameras look along
-z with y up, so the MuJoCo camera frame is the optical frame turned half a turn about x.
Construction validates everything (a rotation that is not one, a non-finite number): errors
name the camera.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

#: The optical frame (OpenCV) -> the MuJoCo camera frame: x kept, y and z flipped.
OPTICAL_TO_MUJOCO = np.diag([1.0, -1.0, -1.0])
_ROTATION_TOL = 1e-4


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels at ``width`` x ``height`` (OpenCV's convention)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics need finite fx, fy > 0, cx, cy; got {values}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"intrinsics need width, height > 0; got {self.width}x{self.height}")

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fovy_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.height / (2.0 * self.fy)))


@dataclass(frozen=True)
class PlacedCamera:
    """A twin camera at a real camera's pose (see the module docstring for the frames)."""

    name: str
    T_world_camera: tuple[tuple[float, float, float, float], ...]
    intrinsics: CameraIntrinsics | None = None
    fovy_deg: float | None = None

    def __post_init__(self) -> None:
        T = np.asarray(self.T_world_camera, dtype=float)
        where = f"camera {self.name!r}"
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"{where}: T_world_camera must be a 4x4 matrix of finite numbers")
        if not np.allclose(T[3], (0.0, 0.0, 0.0, 1.0)):
            raise ValueError(f"{where}: T_world_camera's last row must be [0, 0, 0, 1]")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=_ROTATION_TOL) or np.linalg.det(R) < 0:
            raise ValueError(f"{where}: T_world_camera's top-left 3x3 is not a rotation")
        object.__setattr__(self, "T_world_camera", tuple(tuple(float(v) for v in r) for r in T))
        if (self.intrinsics is None) == (self.fovy_deg is None):
            raise ValueError(f"{where}: give either intrinsics (fx, fy, cx, cy) or fovy_deg")
        if self.fovy_deg is not None and not 0.0 < self.fovy_deg < 180.0:
            raise ValueError(f"{where}: fovy_deg must be in (0, 180), got {self.fovy_deg!r}")

    @classmethod
    def from_pose(
        cls,
        name: str,
        R_world_camera: np.ndarray,
        p_world_camera: Sequence[float],
        intrinsics: CameraIntrinsics | None = None,
        fovy_deg: float | None = None,
    ) -> PlacedCamera:
        """From the optical frame's rotation and position in the world frame."""
        T = np.eye(4)
        T[:3, :3] = R_world_camera
        T[:3, 3] = p_world_camera
        return cls(name, tuple(map(tuple, T)), intrinsics, fovy_deg)

    @property
    def position(self) -> np.ndarray:
        """The camera's position in the world frame (m)."""
        return np.asarray(self.T_world_camera)[:3, 3].copy()

    @property
    def R_world_optical(self) -> np.ndarray:
        """The optical frame's axes (columns) in the world frame."""
        return np.asarray(self.T_world_camera)[:3, :3].copy()

    @property
    def R_world_mujoco(self) -> np.ndarray:
        """The MuJoCo camera frame's axes (columns) in the world frame (what ``cam_xmat`` is)."""
        return self.R_world_optical @ OPTICAL_TO_MUJOCO


def place_camera(spec: mujoco.MjSpec, camera: PlacedCamera) -> None:
    """Put ``camera`` into ``spec``'s world body: the camera of its name is moved there (or
    added). With intrinsics the MuJoCo camera takes them (sensor size = resolution, so one
    pixel is one length unit); MuJoCo's principal offset is measured from the image centre
    towards -x and -y (OpenGL pixel centres), hence ``W/2 - 0.5 - cx``."""
    cam = spec.camera(camera.name)
    if cam is None:
        cam = spec.worldbody.add_camera(name=camera.name)
    elif cam.parent.name != "world":
        raise ValueError(f"camera {camera.name!r} rides on a robot; only fixed cameras are placed")
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, camera.R_world_mujoco.flatten())
    cam.pos = camera.position
    cam.quat = quat
    cam.mode = mujoco.mjtCamLight.mjCAMLIGHT_FIXED
    k = camera.intrinsics
    if k is None:
        cam.fovy = float(camera.fovy_deg)
        cam.sensor_size = [0.0, 0.0]
        return
    cam.resolution = [k.width, k.height]
    cam.sensor_size = [float(k.width), float(k.height)]
    cam.focal_pixel = [k.fx, k.fy]
    cam.principal_pixel = [k.width / 2 - 0.5 - k.cx, k.height / 2 - 0.5 - k.cy]
    cam.fovy = k.fovy_deg  # informational; MuJoCo uses the intrinsics once sensor_size is set
