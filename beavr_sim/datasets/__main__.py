"""``python -m beavr_sim.datasets generate --task T --episodes N --seed S --out DIR``.

Generates LeRobot demonstrations headless from synthesized VR traces run through the full
teleop pipeline (see :mod:`beavr_sim.datasets.generate`). Prints, last, one JSON line.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import asdict
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.naming import UnknownNameError


def parse_cameras(text: str) -> tuple[str, ...]:
    text = text.strip().lower()
    return () if text in ("", "none", "off") else tuple(c.strip() for c in text.split(","))


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
        "--cameras", default="front,overhead", help="cameras to record, comma-separated, or none"
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


def recording_config(args):
    from beavr_sim.datasets.features import RecordingConfig

    height, width = parse_size(args.image_size)
    return RecordingConfig(
        fps=args.fps,
        cameras=parse_cameras(args.cameras),
        image_height=height,
        image_width=width,
        hand_keypoints=not args.no_keypoints,
        episode_seconds=args.episode_seconds,
        use_videos=not args.no_videos,
        environment_state=args.environment_state,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.datasets", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate", help="demonstrations from synthesized VR traces")
    g.add_argument("--task", required=True)
    g.add_argument("--episodes", type=int, default=50)
    g.add_argument("--seed", type=int, default=0, help="first episode seed (then seed+1, ...)")
    g.add_argument("--out", type=Path, required=True, help="dataset root folder")
    g.add_argument("--embodiment", default="xarm7_leap_right")
    g.add_argument("--keep-failed", action="store_true", help="also write failed episodes")
    g.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_args(g)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    from beavr_sim.datasets.generate import generate

    try:
        summary = generate(
            args.task,
            args.episodes,
            args.seed,
            args.out,
            repo_id=args.repo_id,
            embodiment=args.embodiment,
            config=recording_config(args),
            keep_failed=args.keep_failed,
            overwrite=args.overwrite,
            progress=not args.quiet,
        )
    except (UnknownNameError, ValueError, FileExistsError, ImportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(asdict(summary)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
