"""``python -m beavr_sim.bench {sim,retarget,teleop} [--seconds S] [--frames N]``: prints JSON."""

from __future__ import annotations

import argparse
import json
import sys

import beavr_sim  # noqa: F401  (registers the envs)

BENCHMARKS = ("sim", "retarget", "teleop")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.bench", description=__doc__)
    parser.add_argument("benchmark", choices=BENCHMARKS, help="which benchmark to run")
    parser.add_argument(
        "--seconds", type=float, default=2.0, help="time per measurement (default 2)"
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=None,
        help="sim: rendered frames to time (default 20); retarget: trace frames (default all)",
    )
    args = parser.parse_args(argv)
    if args.benchmark == "sim":
        from beavr_sim.bench.sim import run

        print(f"benchmarking simulation ({args.seconds:g} s per measurement)...", file=sys.stderr)
        result = run(seconds=args.seconds, render_frames=args.frames or 20)
    elif args.benchmark == "retarget":
        from beavr_sim.bench.retarget import run as run_retarget

        print("benchmarking LEAP retargeting on the human hand trace...", file=sys.stderr)
        result = run_retarget(frames=args.frames)
    elif args.benchmark == "teleop":
        from beavr_sim.bench.teleop import run as run_teleop

        print("benchmarking the teleop pipeline on bundled VR traces...", file=sys.stderr)
        result = run_teleop()
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
