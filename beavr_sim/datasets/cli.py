"""Command-line options of recording, shared by ``python -m beavr_sim.datasets generate`` and
``python -m beavr_sim.teleop --record`` (library code: entry points import it, never each other).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from beavr_sim.datasets.features import RecordingConfig


def parse_cameras(text: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``--cameras``: ``front,overhead`` (RGB) with ``NAME:depth`` for a camera's depth ->
    (RGB cameras, depth cameras); ``none`` -> nothing."""
    text = text.strip()
    if text.lower() in ("", "none", "off"):
        return (), ()
    rgb: list[str] = []
    depth: list[str] = []
    for item in (c.strip() for c in text.split(",")):
        name, _, kind = item.partition(":")  # the name as given: a placed camera's may be Side
        if kind.lower() not in ("", "depth"):
            raise ValueError(f"--cameras {item!r}: a camera is NAME or NAME:depth")
        (depth if kind else rgb).append(name)
    return tuple(rgb), tuple(depth)


def parse_size(text: str) -> tuple[int, int]:
    """``HxW`` (e.g. 480x640) -> (height, width)."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise ValueError(f"image size must be HxW, e.g. 480x640, got {text!r}")
    return int(parts[0]), int(parts[1])


def add_recording_args(p: argparse.ArgumentParser) -> None:
    """The recording options shared with ``python -m beavr_sim.teleop --record``."""
    p.add_argument("--repo-id", default=None, help="dataset repo id (default beavr_sim/<task>)")
    p.add_argument("--fps", type=int, default=30, help="frame rate = the env's control rate")
    p.add_argument(
        "--cameras",
        default="front,overhead",
        help="twin cameras to record, comma-separated (NAME:depth for a camera's depth, "
        "e.g. front,front:depth), or none",
    )
    p.add_argument("--image-size", default="480x640", help="HxW of recorded images")
    p.add_argument("--no-videos", action="store_true", help="store PNG frames, not video")
    p.add_argument("--no-keypoints", action="store_true", help="leave out the raw hand keypoints")
    p.add_argument(
        "--environment-state",
        action="store_true",
        help="also record object and target poses (observation.environment_state)",
    )
    p.add_argument(
        "--episode-seconds", type=float, default=None, help="episode time limit (default: env's)"
    )


def add_camera_poses_arg(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--camera-poses F.toml``, shared with ``python -m beavr_sim.teleop`` (read with
    :func:`beavr_sim.cameras.poses.load_camera_poses`)."""
    p.add_argument(
        "--camera-poses",
        type=Path,
        default=None,
        metavar="F.toml",
        help="place the twin's cameras at real cameras' poses: the T_world_camera and "
        "intrinsics of F's [cameras.NAME] tables (a rig file; python -m beavr_sim.cameras "
        "calibrate writes them; docs/cameras.md); --cameras may name them",
    )


def recording_config(
    args: argparse.Namespace, placed_cameras: tuple[str, ...] = ()
) -> RecordingConfig:
    """The :class:`RecordingConfig` of options added by :func:`add_recording_args`;
    ``placed_cameras``: names of twin cameras placed in the scene (``--camera-poses``), which
    ``--cameras`` may name too."""
    height, width = parse_size(args.image_size)
    cameras, depth_cameras = parse_cameras(args.cameras)
    return RecordingConfig(
        fps=args.fps,
        cameras=cameras,
        depth_cameras=depth_cameras,
        placed_cameras=placed_cameras,
        image_height=height,
        image_width=width,
        hand_keypoints=not args.no_keypoints,
        episode_seconds=args.episode_seconds,
        use_videos=not args.no_videos,
        environment_state=args.environment_state,
    )
