"""The camera package's errors, importable without LeRobot (the CLI catches them)."""


class CameraSpecError(ValueError):
    """A camera spec or rig table that cannot become a LeRobot camera config."""


class CameraError(RuntimeError):
    """A camera that cannot be opened."""


class CameraStoppedError(RuntimeError):
    """A camera that stopped delivering frames (its newest is too old, or its reader ended)."""


class CalibrationError(ValueError):
    """Calibration images that do not give a camera pose (the board not found, too few views)."""
