"""``python -m beavr_sim.datasets generate --task T --episodes N --seed S --out DIR
[--workers N | --ray [--ray-address ADDRESS]]`` and ``python -m beavr_sim.datasets augment
--source SRC --episodes N --seed S --out DIR [--workers N | --ray] [--cameras ...]``.

Generates LeRobot demonstrations headless from synthesized VR traces run through the full
teleop pipeline (see :mod:`beavr_sim.synthetic.generate`). ``--workers N`` (default: one per
core) runs episodes in N local worker processes, ``--ray`` as Ray tasks; each episode is a shard,
merged in seed order with LeRobot's ``aggregate_datasets`` into the same dataset a serial run
(``--workers 1``) writes. ``augment`` makes the episodes from a recorded dataset instead of the
expert (MimicGen-style, :mod:`beavr_sim.datasets.augment`), with the same runner. Prints, last,
one JSON line.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import asdict
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.cameras.poses import load_camera_poses
from beavr_sim.datasets.augment.source import open_source
from beavr_sim.datasets.cli import (
    add_camera_poses_arg,
    add_recording_args,
    parse_cameras,
    recording_config,
)
from beavr_sim.naming import UnknownNameError
from beavr_sim.scaling.cli import add_scale_args, scale_config
from beavr_sim.scaling.executors import LOG_FORMAT, JobFailed


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
    g.add_argument(
        "--overwrite",
        action="store_true",
        help="start anew: delete the dataset at --out (default: resume it, skipping its seeds)",
    )
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_args(g)
    add_camera_poses_arg(g)
    add_scale_args(g)
    a = sub.add_parser("augment", help="new demonstrations from recorded ones (MimicGen-style)")
    a.add_argument("--source", type=Path, required=True, help="a beavr_sim LeRobot dataset")
    a.add_argument("--episodes", type=int, default=50)
    a.add_argument("--seed", type=int, default=1000, help="first new seed (then seed+1, ...)")
    a.add_argument("--out", type=Path, required=True, help="dataset root folder")
    a.add_argument("--repo-id", default=None, help="dataset repo id (default beavr_sim/<task>)")
    a.add_argument(
        "--cameras", default=None, help="cameras to record, comma-separated, or none (default: "
        "the source's)"
    )  # fmt: skip
    a.add_argument("--overwrite", action="store_true", help="start anew (default: resume)")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    add_scale_args(a)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format=LOG_FORMAT)
    from beavr_sim.synthetic.generate import generate  # local: heavy (mujoco)

    if args.command == "augment":
        return _augment(args, generate)
    try:
        placed = load_camera_poses(args.camera_poses) if args.camera_poses else ()
        summary = generate(
            args.task,
            args.episodes,
            args.seed,
            args.out,
            repo_id=args.repo_id,
            embodiment=args.embodiment,
            config=recording_config(args, tuple(c.name for c in placed)),
            keep_failed=args.keep_failed,
            overwrite=args.overwrite,
            progress=not args.quiet,
            scale=scale_config(args),
            camera_poses=args.camera_poses,
        )
    except (UnknownNameError, ValueError, FileExistsError, FileNotFoundError, ImportError,
            JobFailed) as exc:  # fmt: skip
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(asdict(summary)))
    return 0


def _augment(args: argparse.Namespace, generate) -> int:
    try:
        source = open_source(args.source)
        cameras = None if args.cameras is None else parse_cameras(args.cameras)
        summary = generate(
            source.task,
            args.episodes,
            args.seed,
            args.out,
            repo_id=args.repo_id,
            embodiment=source.embodiment,
            config=source.recording_config(cameras),
            overwrite=args.overwrite,
            progress=not args.quiet,
            scale=scale_config(args),
            source=source.root,
        )
    except (UnknownNameError, ValueError, FileExistsError, FileNotFoundError, ImportError,
            JobFailed) as exc:  # fmt: skip
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(asdict(summary)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
