"""``python -m beavr_sim.eval --policy PATH --task T [--embodiment E] --episodes N --seed S
[--async] [--videos DIR] [--max-seconds S] [--device cpu]``

Loads a LeRobot pretrained policy folder (ACT, Diffusion, SmolVLA, ... through LeRobot's own
factory) and runs it in the task's env. ``--async`` runs BEAVR's think-act loop in real time
(control at the env's rate from an action queue, inference refilling it in a thread). Prints,
last, one JSON line: task, episodes, successes, success_rate, mean_time_s (and with --async the
control-loop jitter and the ticks that found no action ready).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.naming import UnknownNameError


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m beavr_sim.eval",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--policy", type=Path, required=True, help="pretrained_model folder")
    p.add_argument("--task", required=True)
    p.add_argument("--embodiment", default="xarm7_leap_right")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=1000, help="first episode seed")
    p.add_argument("--async", dest="asynchronous", action="store_true", help="think-act loop")
    p.add_argument("--videos", type=Path, default=None, help="write an mp4 per episode here")
    p.add_argument("--max-seconds", type=float, default=None, help="episode limit (env's)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from beavr_sim.eval.policy import LoadedPolicy
    from beavr_sim.eval.runner import evaluate
    from beavr_sim.tasks.registry import canonical_task_name

    try:
        task = canonical_task_name(args.task)
        if args.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
        policy = LoadedPolicy(args.policy, device=args.device)
        summary = evaluate(
            policy,
            task,
            args.embodiment,
            args.episodes,
            args.seed,
            asynchronous=args.asynchronous,
            max_seconds=args.max_seconds,
            videos=args.videos,
            progress=not args.quiet,
        )
    except (UnknownNameError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
