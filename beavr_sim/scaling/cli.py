"""The command-line options of scaling, shared by ``python -m beavr_sim.datasets generate`` and
``python -m beavr_sim.eval``."""

from __future__ import annotations

import argparse

from beavr_sim.scaling.executors import ScaleConfig


def add_scale_args(p: argparse.ArgumentParser, default_workers: int | None = None) -> None:
    p.add_argument(
        "--workers",
        type=int,
        default=default_workers,
        help="local worker processes (default: one per core; 1: in this process); with --ray: "
        "the most episodes in flight (default: the cluster's CPUs)",
    )
    p.add_argument(
        "--ray",
        action="store_true",
        help="run episodes as Ray tasks (pip install -e '.[scale]'); a local Ray unless "
        "--ray-address",
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="an existing Ray cluster: auto, HOST:6379 or ray://HOST:10001 (implies --ray)",
    )
    p.add_argument(
        "--max-attempts",
        type=int,
        default=3,
        help="tries per episode when a worker dies or raises (default 3)",
    )


def scale_config(args: argparse.Namespace) -> ScaleConfig:
    """The :class:`ScaleConfig` of options added by :func:`add_scale_args`."""
    return ScaleConfig(
        workers=args.workers,
        ray=bool(args.ray or args.ray_address),
        ray_address=args.ray_address,
        max_attempts=args.max_attempts,
    )
