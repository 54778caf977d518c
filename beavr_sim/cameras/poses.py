"""Where a rig file's cameras stand: the twin cameras its `[cameras.NAME]` tables place.

A table places the twin camera of its name when it has `T_world_camera` (4x4; the camera's
optical frame, x right, y down, z forward, in the world frame) and either `fx`, `fy`, `cx`,
`cy` (pixels at the table's `width` x `height`) or `fovy_deg`
(:class:`~beavr_sim.envs.camera_pose.PlacedCamera`). Light (no LeRobot import): the session
reads it before building the twin. Errors are one-line `CameraSpecError`s naming the camera.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from beavr_sim.cameras.errors import CameraSpecError
from beavr_sim.envs.camera_pose import CameraIntrinsics, PlacedCamera

#: A rig table's keys placing the twin camera of its name (not LeRobot's).
POSE_KEYS = ("T_world_camera", "fx", "fy", "cx", "cy", "fovy_deg")
_INTRINSICS = ("fx", "fy", "cx", "cy")


def rig_tables(path: str | Path) -> dict[str, dict[str, Any]]:
    """The `[cameras.NAME]` tables of a rig file, by name (none: {})."""
    with open(path, "rb") as f:
        tables = tomllib.load(f).get("cameras", {})
    if not isinstance(tables, dict) or not all(isinstance(t, dict) for t in tables.values()):
        raise CameraSpecError(f"{path}: [cameras] must hold one [cameras.NAME] table per camera")
    return tables


def placed_camera(name: str, table: dict[str, Any]) -> PlacedCamera | None:
    """The twin camera a rig's `[cameras.NAME]` table places, or None when it has no pose."""
    given = [k for k in POSE_KEYS if k in table]
    if not given:
        return None
    if "T_world_camera" not in table:
        raise CameraSpecError(
            f"camera {name!r}: {given} place the twin camera only with T_world_camera "
            "(4x4, the optical frame in the world frame)"
        )
    intrinsics = None
    if any(k in table for k in _INTRINSICS):
        missing = [k for k in (*_INTRINSICS, "width", "height") if k not in table]
        if missing or "fovy_deg" in table:
            raise CameraSpecError(
                f"camera {name!r}: intrinsics need all of fx, fy, cx, cy, width, height "
                f"(missing {missing}) and no fovy_deg"
            )
    elif "fovy_deg" not in table:
        raise CameraSpecError(
            f"camera {name!r}: T_world_camera needs the field of view: fx, fy, cx, cy "
            "(with width, height) or fovy_deg"
        )
    try:
        if "fx" in table:
            intrinsics = CameraIntrinsics(
                *(float(table[k]) for k in _INTRINSICS), int(table["width"]), int(table["height"])
            )
        fovy = float(table["fovy_deg"]) if "fovy_deg" in table else None
        return PlacedCamera(name, table["T_world_camera"], intrinsics=intrinsics, fovy_deg=fovy)
    except (ValueError, TypeError) as exc:
        text = str(exc)
        prefix = "" if text.startswith(f"camera {name!r}") else f"camera {name!r}: "
        raise CameraSpecError(prefix + text) from None


def rig_placed_cameras(path: str | Path) -> tuple[PlacedCamera, ...]:
    """The twin cameras a rig file's `[cameras.NAME]` tables place (those with a pose)."""
    placed = (placed_camera(name, table) for name, table in rig_tables(path).items())
    return tuple(p for p in placed if p is not None)


def load_camera_poses(path: str | Path) -> tuple[PlacedCamera, ...]:
    """``--camera-poses F.toml`` (teleop and ``datasets generate``): the twin cameras F
    places; a file that places none is an error (it was given to place some)."""
    placed = rig_placed_cameras(path)
    if not placed:
        raise CameraSpecError(
            f"--camera-poses {path}: no [cameras.NAME] table has a T_world_camera (docs/cameras.md)"
        )
    return placed
