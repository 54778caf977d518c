"""Real cameras through LeRobot's camera classes: spec parsing and a CameraSet that owns them."""

from beavr_sim.cameras.camera_set import CameraError, CameraSet, CameraStats, Grab
from beavr_sim.cameras.spec import CameraSpecError, parse_camera_arg, parse_camera_table

__all__ = [
    "CameraError",
    "CameraSet",
    "CameraSpecError",
    "CameraStats",
    "Grab",
    "parse_camera_arg",
    "parse_camera_table",
]
