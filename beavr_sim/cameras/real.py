"""RealCameras: owns the session's LeRobot cameras and hands the control thread their newest frames.

Capture runs on LeRobot's own background read threads (started by `connect()`; `async_read` /
`read_latest` are the reads); this module never captures. `grab()` is non-blocking and never
raises: per camera it returns the newest frame and its capture age, counts frames older than
`stale_after_s` (1.5 control periods) and repeats of an already-returned frame, and reports a
camera as dead once its newest frame is older than `dead_after_s` or its read thread has stopped.
A dead camera yields no frame: the caller ends the episode as a hardware fault (a teleop
session) or raises (the LeRobot robot). `peek()` is the same read for a viewer's thread (the
camera stream): it counts nothing.
`connect()` fails with a one-line `CameraError` naming the camera and what to check; a config
that states `width` and `height` must get frames of that size (a video file is not set to them:
OpenCV cannot resize or re-time a file, so they are checked against its frames instead).

Depth: a camera configured with depth (LeRobot's RealSense `use_depth`) gives, with each colour
frame, the depth map of the same capture (LeRobot's `latest_depth_frame`: HxWx1 uint16
millimetres) as its own image feature `NAME_depth`, LeRobot's name for it; `names` lists the
features a grab returns (each camera's, then the depth ones), `frame_shape` their shapes.
A camera is recorded with its colour image: `use_rgb = false` is refused at construction.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from lerobot.cameras.camera import Camera
from lerobot.cameras.configs import CameraConfig
from lerobot.cameras.opencv.configuration_opencv import OpenCVCameraConfig
from lerobot.cameras.realsense.configuration_realsense import RealSenseCameraConfig
from lerobot.cameras.utils import make_cameras_from_configs
from lerobot.cameras.zmq.configuration_zmq import ZMQCameraConfig

from beavr_sim.cameras.errors import CameraError, CameraSpecError

log = logging.getLogger(__name__)

DEAD_AFTER_S = 1.0
FIRST_FRAME_TIMEOUT_S = 5.0
#: LeRobot's suffix of a camera's depth feature (``NAME_depth``, as its robots name it).
DEPTH_SUFFIX = "_depth"


@dataclass
class CameraStats:
    """Per-camera counts for one episode (reset by `RealCameras.start_episode`)."""

    frames: int = 0
    stale: int = 0
    repeats: int = 0
    ages_s: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, float | int]:
        ages = np.asarray(self.ages_s) if self.ages_s else np.zeros(1)
        return {
            "frames": self.frames,
            "stale": self.stale,
            "repeats": self.repeats,
            "age_p50_ms": round(float(np.percentile(ages, 50)) * 1e3, 2),
            "age_p99_ms": round(float(np.percentile(ages, 99)) * 1e3, 2),
        }


@dataclass(frozen=True)
class Grab:
    """One grab across all cameras: frames by feature name (live cameras only: a depth
    camera's colour frame and its ``NAME_depth`` map of the same capture) and the names of
    dead cameras."""

    frames: dict[str, np.ndarray]
    ages_s: dict[str, float]
    dead: tuple[str, ...]


def _what_to_check(config: CameraConfig) -> str:
    if isinstance(config, OpenCVCameraConfig):
        return f"check that {config.index_or_path} exists and is readable (lerobot-find-cameras opencv)"
    if isinstance(config, RealSenseCameraConfig):
        return f"check that RealSense {config.serial_number_or_name} is plugged in (lerobot-find-cameras realsense)"
    if isinstance(config, ZMQCameraConfig):
        return f"check that an image server answers on {config.server_address}:{config.port}"
    return "check the camera's config"


def _source_config(config: CameraConfig) -> CameraConfig:
    """The config the camera opens with: a video file's size and rate are the file's own
    (OpenCV refuses to set them), so they are left out and checked against its frames."""
    if (
        isinstance(config, OpenCVCameraConfig)
        and isinstance(config.index_or_path, Path)
        and config.index_or_path.is_file()
    ):
        return dataclasses.replace(config, width=None, height=None, fps=None)
    return config


class RealCameras:
    """The session's real cameras; one instance per session, `close()` when done."""

    def __init__(
        self,
        configs: dict[str, CameraConfig],
        control_period_s: float,
        dead_after_s: float = DEAD_AFTER_S,
        *,
        make_cameras: Callable[[dict[str, CameraConfig]], dict[str, Camera]] = (
            make_cameras_from_configs
        ),
    ) -> None:
        if control_period_s <= 0:
            raise ValueError(f"control_period_s must be > 0, got {control_period_s}")
        self.configs = dict(configs)
        #: The cameras whose depth is recorded too (LeRobot's ``use_depth``).
        self.depth_cameras = tuple(n for n, c in self.configs.items() if _uses_depth(c))
        _check_depth_configs(self.configs, self.depth_cameras)
        self._make = make_cameras
        self.stale_after_s = 1.5 * control_period_s
        self.dead_after_s = dead_after_s
        self._cameras: dict[str, Camera] = {}
        self._last_stamp: dict[str, float | None] = {}
        self.stats: dict[str, CameraStats] = {}

    @property
    def cameras(self) -> tuple[str, ...]:
        """The cameras' names."""
        return tuple(self.configs)

    @property
    def names(self) -> tuple[str, ...]:
        """The image features a grab returns: each camera's, then ``NAME_depth`` of each
        depth camera."""
        return self.cameras + tuple(n + DEPTH_SUFFIX for n in self.depth_cameras)

    def connect(self) -> None:
        """Open every camera and wait for its first frame; one-line `CameraError` otherwise."""
        _camera_thread_errors_in_one_line()
        for name, config in self.configs.items():
            try:
                camera = self._make({name: _source_config(config)})[name]
                # LeRobot's ZMQ warm-up checks for a frame the instant its read thread starts
                # (with warmup_s = 0: a race); the image server is warm, and the first frame
                # is waited for below.
                camera.connect(warmup=not isinstance(config, ZMQCameraConfig))
                self._cameras[name] = camera
                self._wait_first_frame(camera, config)
            except Exception as exc:
                self.close()
                first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                check = "" if isinstance(exc, _WrongFrameSize) else f"; {_what_to_check(config)}"
                raise CameraError(
                    f"camera {name!r} ({config.type}) failed to start: {first}{check}"
                ) from None
        self.start_episode()

    @staticmethod
    def _wait_first_frame(camera: Camera, config: CameraConfig) -> None:
        deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
        depth = _uses_depth(config)
        while time.monotonic() < deadline:
            frame, depth_map, _ = _newest_of(camera, depth)
            if frame is not None and (depth_map is not None or not depth):
                _check_frame_size(frame, config)
                if depth_map is not None:
                    _check_frame_size(depth_map, config, "depth maps")
                return
            time.sleep(0.01)
        raise TimeoutError(f"no frame within {FIRST_FRAME_TIMEOUT_S:.0f} s")

    def frame_shape(self, name: str) -> tuple[int, int, int]:
        """(height, width, 3) of a connected camera's frames; (height, width, 1) of a depth
        feature (``NAME_depth``)."""
        if name not in self.configs and name.endswith(DEPTH_SUFFIX):
            camera = self._cameras[name.removesuffix(DEPTH_SUFFIX)]
            return (int(camera.height), int(camera.width), 1)
        camera = self._cameras[name]
        return (int(camera.height), int(camera.width), 3)

    def start_episode(self) -> None:
        self.stats = {name: CameraStats() for name in self.configs}
        self._last_stamp = {name: None for name in self.configs}

    def grab(self) -> Grab:
        """Newest frame of each camera, non-blocking; never raises."""
        frames: dict[str, np.ndarray] = {}
        ages: dict[str, float] = {}
        dead: list[str] = []
        now = time.perf_counter()
        for name, camera in self._cameras.items():
            frame, depth, stamp = self._newest(name, camera)
            if frame is None or stamp is None or now - stamp > self.dead_after_s:
                dead.append(name)
                continue
            age = max(0.0, now - stamp)
            stats = self.stats[name]
            stats.frames += 1
            stats.ages_s.append(age)
            if age > self.stale_after_s:
                stats.stale += 1
            if stamp == self._last_stamp[name]:
                stats.repeats += 1
            self._last_stamp[name] = stamp
            frames[name] = frame
            if depth is not None:
                frames[name + DEPTH_SUFFIX] = depth
            ages[name] = age
        return Grab(frames=frames, ages_s=ages, dead=tuple(dead))

    def peek(self) -> Grab:
        """Newest frame (and depth map) of each camera for a viewer (any thread): counts
        nothing; never raises."""
        frames: dict[str, np.ndarray] = {}
        ages: dict[str, float] = {}
        dead: list[str] = []
        now = time.perf_counter()
        for name, camera in list(self._cameras.items()):
            try:
                frame, depth, stamp = self._newest(name, camera)
            except Exception:
                frame, depth, stamp = None, None, None
            if frame is None or stamp is None or now - stamp > self.dead_after_s:
                dead.append(name)
                continue
            frames[name], ages[name] = frame, max(0.0, now - stamp)
            if depth is not None:
                frames[name + DEPTH_SUFFIX] = depth
        return Grab(frames=frames, ages_s=ages, dead=tuple(dead))

    def _newest(
        self, name: str, camera: Camera
    ) -> tuple[np.ndarray | None, np.ndarray | None, float | None]:
        """The newest colour frame, depth map (a depth camera's; None for the others: a
        depth camera without one yields no frame) and capture time; all None once the
        camera's read thread stopped."""
        thread = getattr(camera, "thread", None)
        if thread is None or not thread.is_alive():
            return None, None, None
        depth = name in self.depth_cameras
        frame, depth_map, stamp = _newest_of(camera, depth)
        if depth and depth_map is None:
            return None, None, stamp
        return frame, depth_map, stamp

    def failed_for_good(self) -> list[str]:
        """Cameras whose LeRobot read thread has stopped (they will not come back)."""
        return [
            name
            for name, camera in self._cameras.items()
            if getattr(camera, "thread", None) is None or not camera.thread.is_alive()
        ]

    def summary(self) -> dict[str, dict[str, float | int]]:
        return {name: stats.summary() for name, stats in self.stats.items()}

    def close(self) -> None:
        for camera in self._cameras.values():
            try:
                if camera.is_connected:
                    camera.disconnect()
            except Exception:
                pass
        self._cameras.clear()


def _uses_depth(config: CameraConfig) -> bool:
    return bool(getattr(config, "use_depth", False))


def _check_depth_configs(configs: dict[str, CameraConfig], depth: tuple[str, ...]) -> None:
    for name, config in configs.items():
        if not getattr(config, "use_rgb", True):
            raise CameraSpecError(
                f"camera {name!r}: use_rgb = false is not supported (a real camera records its "
                "colour image; use_depth = true adds its depth as "
                f"{name}{DEPTH_SUFFIX})"
            )
    for name in depth:
        if name + DEPTH_SUFFIX in configs:
            raise CameraSpecError(
                f"camera {name + DEPTH_SUFFIX!r} is also camera {name!r}'s depth feature; rename it"
            )


def _newest_of(
    camera: Camera, depth: bool
) -> tuple[np.ndarray | None, np.ndarray | None, float | None]:
    """A LeRobot camera's newest buffered colour frame (RealSense's ``latest_color_frame``,
    the others' ``latest_frame``), depth map (``depth``: RealSense's ``latest_depth_frame``)
    and capture time, read together under its frame lock (one capture)."""
    with camera.frame_lock:
        frame = getattr(camera, "latest_color_frame", None)
        if frame is None:
            frame = getattr(camera, "latest_frame", None)
        depth_map = getattr(camera, "latest_depth_frame", None) if depth else None
        return frame, depth_map, camera.latest_timestamp


class _WrongFrameSize(ValueError):
    """A camera's frames are not the size its config states."""


def _check_frame_size(frame: np.ndarray, config: CameraConfig, what: str = "frames") -> None:
    if config.width is None or config.height is None:
        return
    height, width = frame.shape[:2]
    if (height, width) != (config.height, config.width):
        raise _WrongFrameSize(
            f"its {what} are width={width} x height={height}, not the configured "
            f"width={config.width} x height={config.height}; set width and height to the camera's"
        )


def _camera_thread_errors_in_one_line() -> None:
    """A LeRobot camera's read thread (named ``<camera>_read_loop``) ends by raising when its
    camera stops (a video file's end, a pulled cable); Python would print that traceback on
    stderr. Log it as one line instead (:meth:`RealCameras.grab` reports the camera dead); any
    other thread's exception goes to the hook that was there. Idempotent."""
    previous = threading.excepthook
    if getattr(previous, "_beavr_camera_hook", False):
        return

    def hook(args: threading.ExceptHookArgs) -> None:
        name = args.thread.name if args.thread is not None else ""
        if name.endswith("_read_loop") and args.exc_type is not SystemExit:
            camera = name.removesuffix("_read_loop")
            text = str(args.exc_value)
            log.warning("camera stopped: %s", text if camera in text else f"{camera}: {text}")
        else:
            previous(args)

    hook._beavr_camera_hook = True  # type: ignore[attr-defined]
    threading.excepthook = hook
