"""``python -m beavr_sim.experts --task pour --episodes 50 --seed 0 [--embodiment E] [--render DIR]``

Runs the task's scripted expert; shows a progress bar, then prints one JSON line:
``{"task", "embodiment", "episodes", "successes", "success_rate", "mean_time_s"}``
(``mean_time_s``: mean episode time of the successful episodes, null if none).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.experts.run import run_expert
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT
from beavr_sim.tasks.registry import canonical_task_name


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m beavr_sim.experts",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--task", required=True, help="task name, e.g. PickupBox or pour")
    parser.add_argument("--episodes", type=int, default=50, help="episodes to run (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument("--embodiment", default=DEFAULT_EMBODIMENT, help="robot embodiment")
    parser.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="DIR",
        help="save one front-camera video per episode in DIR",
    )
    parser.add_argument("--verbose", action="store_true", help="print each episode's result")
    args = parser.parse_args(argv)

    try:
        task = canonical_task_name(args.task)
        report, results = run_expert(task, args.embodiment, args.episodes, args.seed, args.render)
    except (UnknownNameError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.verbose:
        for r in results:
            print(
                f"seed {r.seed}: {'success' if r.success else 'FAIL'} {r.seconds:.1f}s {r.details}",
                file=sys.stderr,
            )
    print(report.to_json())
    return 0


if __name__ == "__main__":
    sys.exit(main())
