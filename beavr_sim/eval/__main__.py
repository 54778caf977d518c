"""``python -m beavr_sim.eval --policy PATH [PATH ...] --task T [T ...] [--embodiment E]
--episodes N --seed S [--workers N | --ray [--ray-address A]] [--async] [--videos DIR]
[--max-seconds S] [--device cpu] [--table FILE.csv|FILE.md]``

Loads LeRobot pretrained policy folders (ACT, Diffusion, SmolVLA, ... through LeRobot's own
factory) and runs each in each task's env for N episodes (the same seeds for every pair).
``--workers N`` (default: one per core; 1: in this process) runs episodes in N local worker
processes, ``--ray`` as Ray tasks. ``--async`` runs BEAVR's think-act loop in real time (control
at the env's rate from an action queue, inference refilling it in a thread).

Prints, last, one JSON line: ``results``, one row per (policy, task) with episodes, successes,
success_rate, success_ci95 (Wilson score interval, 95 %), mean_time_s,
mean_success_time_s (over the successful episodes; None without one) (and with --async the
control-loop jitter and the ticks that found no action ready); with a single (policy, task),
that row's keys also stand at the top level. ``--table`` writes the rows as CSV or markdown.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.naming import UnknownNameError
from beavr_sim.scaling.cli import add_scale_args, scale_config
from beavr_sim.scaling.executors import LOG_FORMAT, JobFailed
from beavr_sim.tasks.registry import canonical_task_name


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m beavr_sim.eval",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--policy", type=Path, nargs="+", required=True, help="pretrained_model folder(s)"
    )
    p.add_argument("--task", nargs="+", required=True, help="task name(s)")
    p.add_argument("--embodiment", default="xarm7_leap_right")
    p.add_argument("--episodes", type=int, default=10, help="episodes per (policy, task)")
    p.add_argument("--seed", type=int, default=1000, help="first episode seed")
    p.add_argument("--async", dest="asynchronous", action="store_true", help="think-act loop")
    p.add_argument("--videos", type=Path, default=None, help="write an mp4 per episode here")
    p.add_argument("--max-seconds", type=float, default=None, help="episode limit (env's)")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--table",
        type=Path,
        action="append",
        default=[],
        help="write the result table to FILE.csv or FILE.md (repeatable)",
    )
    p.add_argument("--quiet", action="store_true")
    add_scale_args(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format=LOG_FORMAT)
    from beavr_sim.eval.sweep import sweep, write_table  # local: heavy (mujoco)

    try:
        tasks = list(dict.fromkeys(canonical_task_name(t) for t in args.task))
        for table in args.table:
            if table.suffix not in (".csv", ".md"):
                raise ValueError(f"--table ends in .csv or .md, got {table.name!r}")
        if args.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
        result = sweep(
            args.policy,
            tasks,
            args.embodiment,
            args.episodes,
            args.seed,
            scale=scale_config(args),
            asynchronous=args.asynchronous,
            max_seconds=args.max_seconds,
            videos=args.videos,
            device=args.device,
            progress=not args.quiet,
        )
    except (UnknownNameError, ValueError, FileNotFoundError, ImportError, JobFailed) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for table in args.table:
        write_table(result["results"], table)
    if len(result["results"]) == 1:
        result = {**result["results"][0], **result}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
