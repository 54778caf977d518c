"""Camera specs -> LeRobot camera configs.

Two sources, one parser, one result (`dict[name, lerobot CameraConfig]`):
- a rig file's `[cameras.NAME]` table with LeRobot's config keys (`type`, `fps`, `width`,
  `height`, plus the type's own keys such as `index_or_path`, `serial_number_or_name`,
  `server_address`, `port`, `use_depth`): `parse_camera_table`;
- CLI `--camera NAME=SPEC`, SPEC `opencv:INDEX_OR_PATH`, `realsense:SERIAL` or `zmq:HOST:PORT`,
  optionally suffixed `@WIDTHxHEIGHT`, then `+depth` (a RealSense's depth, the table's
  `use_depth = true`): `spec_table` turns the spec into the table it stands for, which
  `parse_camera_table` reads, so the two forms give equal configs.
A rig table may also carry where the camera stands, for the twin camera of its name
(`beavr_sim.envs.camera_pose.PlacedCamera`): `T_world_camera` (4x4, the camera's optical frame
x right, y down, z forward, in the world frame) and `fx`, `fy`, `cx`, `cy` (pixels at `width` x
`height`) or `fovy_deg`; `beavr_sim.cameras.poses` reads them, `parse_camera_table` leaves them
out.
A camera's name is kept as given, case too (`--camera Front=...` records
`observation.images.Front`): letters, digits or _ (LeRobot's only rule for a feature name is
no `/`; ours keeps names usable as folder names and in `--camera-poses` tables).
Every error is a `CameraSpecError` with one line naming the camera and listing the valid choices.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

from lerobot.cameras.configs import CameraConfig
from lerobot.cameras.opencv.configuration_opencv import OpenCVCameraConfig
from lerobot.cameras.realsense.configuration_realsense import RealSenseCameraConfig
from lerobot.cameras.zmq.configuration_zmq import ZMQCameraConfig

from beavr_sim.cameras.errors import CameraSpecError
from beavr_sim.cameras.poses import POSE_KEYS, rig_tables

DEFAULT_FPS = 30
_NAME = re.compile(r"^[A-Za-z0-9_]+$")
_SIZE = re.compile(r"^(\d+)x(\d+)$")

# SPEC prefix / rig `type` -> LeRobot config class.
CONFIG_TYPES: dict[str, type[CameraConfig]] = {
    "opencv": OpenCVCameraConfig,
    "realsense": RealSenseCameraConfig,
    "intelrealsense": RealSenseCameraConfig,
    "zmq": ZMQCameraConfig,
}
#: The `--camera` SPEC forms (the CLI help and errors say them).
SPEC_FORMS = (
    "opencv:INDEX_OR_PATH, realsense:SERIAL or zmq:HOST:PORT, optionally @WIDTHxHEIGHT, "
    "then +depth on a realsense"
)
#: The `--camera` SPEC's last part asking for the camera's depth (a rig table's `use_depth`).
DEPTH_FLAG = "+depth"


def check_camera_name(name: str, source: str) -> None:
    """A camera name is letters, digits or _ (it becomes ``observation.images.NAME``)."""
    if not _NAME.match(name):
        raise CameraSpecError(f"camera {name!r} ({source}): name must be letters, digits or _")


def parse_camera_arg(arg: str, fps: int = DEFAULT_FPS) -> tuple[str, CameraConfig]:
    """`NAME=SPEC` from the command line -> (name, LeRobot config), through the rig table the
    spec stands for (:func:`spec_table`), so both forms give the same config."""
    name, sep, spec = arg.partition("=")
    if not sep or not name or not spec:
        raise CameraSpecError(f"--camera {arg!r}: expected NAME=SPEC with SPEC {SPEC_FORMS}")
    check_camera_name(name, "--camera")
    return name, parse_camera_table(name, spec_table(name, spec, fps))


def spec_table(name: str, spec: str, fps: int = DEFAULT_FPS) -> dict[str, Any]:
    """A `--camera` SPEC -> the rig `[cameras.NAME]` table it stands for (LeRobot's keys)."""
    depth = spec.endswith(DEPTH_FLAG)
    spec = spec.removesuffix(DEPTH_FLAG)
    if DEPTH_FLAG in spec:
        raise CameraSpecError(
            f"camera {name!r}: {DEPTH_FLAG} goes last (realsense:SERIAL@WIDTHxHEIGHT{DEPTH_FLAG})"
        )
    spec, at, size = spec.partition("@")
    table: dict[str, Any] = {"fps": fps}
    if at:
        match = _SIZE.match(size)
        if match is None:
            raise CameraSpecError(
                f"camera {name!r}: size {size!r} is not WIDTHxHEIGHT (e.g. 640x480)"
            )
        table["width"], table["height"] = int(match.group(1)), int(match.group(2))
    kind, colon, target = spec.partition(":")
    if kind not in ("opencv", "realsense", "zmq") or not colon or not target:
        raise CameraSpecError(f"camera {name!r}: spec {spec!r} is not one of {SPEC_FORMS}")
    table["type"] = kind
    if depth:
        table["use_depth"] = True  # parse_camera_table refuses it on a type without depth
    if kind == "opencv":
        if target.isdigit():
            return {**table, "index_or_path": int(target)}
        # A video file plays at its own rate; OpenCV cannot set a file's fps.
        return {**table, "index_or_path": target, "fps": None}
    if kind == "realsense":
        if not at:  # LeRobot's RealSense takes fps, width and height together (fps is given)
            raise CameraSpecError(
                f"camera {name!r}: a realsense spec needs its size: "
                f"realsense:{target}@WIDTHxHEIGHT (e.g. @640x480)"
            )
        return {**table, "serial_number_or_name": target}
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        raise CameraSpecError(f"camera {name!r}: zmq spec {target!r} is not HOST:PORT")
    # The image server's camera is already warm; a second without a message is a dead
    # server (RealCameras reports it), so LeRobot's read need not block longer.
    return {**table, "server_address": host, "port": int(port), "warmup_s": 0, "timeout_ms": 1000}


def parse_camera_table(name: str, table: dict[str, Any]) -> CameraConfig:
    """A rig file's `[cameras.NAME]` table -> LeRobot config (keys are LeRobot's)."""
    check_camera_name(name, "rig [cameras]")
    values = {k: v for k, v in table.items() if k not in POSE_KEYS}
    kind = values.pop("type", None)
    if kind not in CONFIG_TYPES:
        raise CameraSpecError(
            f"camera {name!r}: type {kind!r} is not one of {sorted(CONFIG_TYPES)}"
        )
    cls = CONFIG_TYPES[kind]
    if "use_depth" in values and not _has_depth(cls):
        raise CameraSpecError(
            f"camera {name!r}: type {kind!r} has no depth (use_depth, {DEPTH_FLAG}); "
            f"types with depth: {', '.join(depth_types())}"
        )
    valid = sorted(f.name for f in dataclasses.fields(cls))
    unknown = sorted(set(values) - set(valid))
    if unknown:
        raise CameraSpecError(
            f"camera {name!r}: unknown keys {unknown} for type {kind!r}; "
            f"valid: {valid + sorted(POSE_KEYS)}"
        )
    values.setdefault("fps", DEFAULT_FPS)
    if cls is ZMQCameraConfig:
        values.setdefault("camera_name", name)
    if cls is OpenCVCameraConfig and isinstance(values.get("index_or_path"), str):
        values["index_or_path"] = Path(values["index_or_path"])
    try:
        return cls(**values)
    except (ValueError, TypeError) as exc:
        raise CameraSpecError(f"camera {name!r}: {exc}") from None


def _has_depth(cls: type[CameraConfig]) -> bool:
    return any(f.name == "use_depth" for f in dataclasses.fields(cls))


def depth_types() -> list[str]:
    """The camera types that have depth (LeRobot's ``use_depth``)."""
    return sorted(kind for kind, cls in CONFIG_TYPES.items() if _has_depth(cls))


def merge_cameras(
    rig: dict[str, CameraConfig], cli: dict[str, CameraConfig], cli_source: str = "--camera"
) -> dict[str, CameraConfig]:
    """Rig cameras plus the command line's (``cli_source``: the flag or field naming them); a
    name given twice is an error, not a silent override."""
    both = sorted(set(rig) & set(cli))
    if both:
        raise CameraSpecError(
            f"camera {both[0]!r} is named both in the rig file and by {cli_source}"
        )
    folded = {name.casefold(): name for name in rig}
    for name in cli:
        if name.casefold() in folded:
            raise CameraSpecError(
                f"camera {name!r} ({cli_source}) and {folded[name.casefold()]!r} (rig file) "
                "differ only in case (their dataset folders collide on case-insensitive file "
                "systems); rename one"
            )
    return {**rig, **cli}


def rig_cameras(path: str | Path) -> dict[str, CameraConfig]:
    """The `[cameras.NAME]` tables of a rig file (none: {})."""
    return {name: parse_camera_table(name, table) for name, table in rig_tables(path).items()}


def session_cameras(
    camera_args: tuple[str, ...], rig_file: str | Path | None, fps: int
) -> dict[str, CameraConfig]:
    """A session's real cameras: the rig file's (when mirroring) plus `--camera` ones."""
    cli = dict(parse_camera_arg(arg, fps) for arg in camera_args)
    if len(cli) != len(camera_args):
        raise CameraSpecError("--camera: the same camera NAME given twice")
    rig = rig_cameras(rig_file) if rig_file is not None else {}
    return merge_cameras(rig, cli)
