"""Real cameras through LeRobot's camera classes: spec parsing and a RealCameras that owns them."""

from beavr_sim.cameras.real import CameraError, RealCameras, CameraStats, Grab
from beavr_sim.cameras.spec import CameraSpecError, parse_camera_arg, parse_camera_table

__all__ = [
    "CameraError",
    "RealCameras",
    "CameraSpecError",
    "CameraStats",
    "Grab",
    "parse_camera_arg",
    "parse_camera_table",
]
