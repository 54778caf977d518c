"""``python -m beavr_sim.bench {sim,retarget,teleop,view,hardware} [--seconds S] [--frames N] [--plot DIR]``:
prints JSON; ``--plot DIR`` also writes latency / timing histograms (PNG) into DIR.

``python -m beavr_sim.bench tracking [--frames N]``: motion-to-motion lag and tracking error
per stage (raw hand -> filtered target -> IK hand -> simulated hand) on bundled traces, on
the virtual clock, and joint ramp lags of the xArm twin (``bench/tracking.py``); JSON.

``python -m beavr_sim.bench latency [--config 1|2|3|4 | --sweep] [--seconds S] [--json]
[--no-mirror] [--plot DIR]``: end-to-end latency of the ``--multiprocess`` pipeline fed the
Quest app's protocol (``bench/latency.py``; ``--sweep``: 1, 2, 4 and 8 hand effectors at 90 Hz
in concurrent sessions): a table on stderr (not with ``--json``), JSON on the last stdout
line.

``python -m beavr_sim.bench contact [--contact CONE:IMPRATIO,...] [--tasks T,...]
[--episodes N]``: contact settings compared on the grasping experts (success, slip of the held
object in the hand, ms per env step; ``bench/contact.py``); JSON.

``python -m beavr_sim.bench scaling [--episodes N] [--workers 1,2] [--ray] ...``: generation
with 1 and N local workers (and Ray), and where a replay tick goes (``bench/scaling.py``,
its own options: ``python -m beavr_sim.bench scaling --help``); JSON on the last line.

``python -m beavr_sim.bench mutations [--only NAME,...] [--list] [--json FILE]``: one planted
bug per safety rule, each in a copy of the repository, against the tests that claim the rule
(``bench/mutations.py``, its own options); a table and caught / total.

``python -m beavr_sim.bench cameras [--runs N] [--seconds S]``: two
480x640 cameras at 30 fps recorded in lockstep: capture-to-record age, the recording's rate and
the cameras' cost to the control tick, with and without (``bench/cameras.py``); JSON on the
last line.

``python -m beavr_sim.bench policies [--tasks T,...] [--policies act,diffusion] [--demos N]
[--episodes N] [--quick] [--out DIR] [--resume]``: demonstrations -> ``lerobot-train`` ->
checkpoint chosen on validation seeds -> success on held-out test seeds with Wilson 95 %
intervals, beside the scripted expert through the teleop pipeline; every stage cached in DIR
(``bench/policies/``, its own options); a markdown table and JSON.

``python -m beavr_sim.bench soak --minutes N``: a looping trace mirrored to the emulated rig
for N minutes; the resident memory's slope after warm-up in MB per hour (target <= 1;
``bench/soak.py``, its own options); JSON on the last line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.bench.hardware import run as run_hardware
from beavr_sim.bench.mutations import main as mutations_main
from beavr_sim.bench.plots import write as write_plots
from beavr_sim.bench.plots import write_latency
from beavr_sim.bench.policies.cli import main as policies_main
from beavr_sim.bench.scaling import main as scaling_main
from beavr_sim.bench.soak import main as soak_main
from beavr_sim.bench.teleop import run as run_teleop
from beavr_sim.bench.tracking import run as run_tracking
from beavr_sim.bench.view import run as run_view

BENCHMARKS = (
    "sim",
    "retarget",
    "teleop",
    "view",
    "hardware",
    "latency",
    "tracking",
    "contact",
    "scaling",
    "mutations",
    "soak",
    "cameras",
    "policies",
)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["scaling"]:  # options of its own
        return scaling_main(argv[1:])
    if argv[:1] == ["mutations"]:  # options of its own
        return mutations_main(argv[1:])
    if argv[:1] == ["cameras"]:  # options of its own
        from beavr_sim.bench.cameras import main as cameras_main  # local: heavy (OpenCV)

        return cameras_main(argv[1:])
    if argv[:1] == ["soak"]:  # options of its own
        return soak_main(argv[1:])
    if argv[:1] == ["policies"]:  # options of its own
        return policies_main(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.bench", description=__doc__)
    parser.add_argument("benchmark", choices=BENCHMARKS, help="which benchmark to run")
    parser.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="time per measurement (default 2); teleop: length of the real-time replay (default 5)",
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=None,
        help="sim: rendered frames to time (default 20); retarget: trace frames (default all); "
        "teleop, tracking: control ticks per trace on the virtual clock (default: the whole trace)",
    )
    parser.add_argument(
        "--plot",
        type=Path,
        default=None,
        metavar="DIR",
        help="write histograms of the measured samples (PNG) into DIR (created); see "
        "docs/benchmarks.md for the file names",
    )
    parser.add_argument(
        "--config",
        type=int,
        choices=(1, 2, 3, 4),
        default=1,
        help="latency: 1 = xArm7+LEAP at 30 Hz, 2 = the same at 90 Hz, 3 = bimanual at 30 Hz, "
        "4 = RX-1 at 90 Hz (headset stream rate)",
    )
    parser.add_argument(
        "--json", action="store_true", help="latency: JSON only (no table on stderr)"
    )
    parser.add_argument(
        "--no-mirror",
        action="store_true",
        help="latency: without mirroring to the emulated hardware",
    )
    parser.add_argument(
        "--layout",
        choices=("processes", "single"),
        default="processes",
        help="latency: the --multiprocess runner (operator and twin processes; default) "
        "or the single-process runner (python -m beavr_sim.teleop's default)",
    )
    parser.add_argument(
        "--sweep",
        action="store_true",
        help="latency: 1, 2, 4 and 8 hand effectors at 90 Hz (concurrent sessions sharing this "
        "machine's cores) instead of one --config; --seconds per effector count",
    )
    parser.add_argument("--sweep-counts", default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--episodes", type=int, default=16, help="contact: expert episodes per task and setting"
    )
    parser.add_argument(
        "--contact",
        default=None,
        metavar="CONE:IMPRATIO,...",
        help="contact: the settings to compare (default pyramidal:1,elliptic:10,pyramidal:10)",
    )
    parser.add_argument(
        "--tasks",
        default=None,
        help="contact: comma-separated tasks (default PickupBox,PickPlace,StackBlocks,Pour)",
    )
    args = parser.parse_args(argv)
    if args.benchmark == "contact":
        from beavr_sim.bench import contact  # local: heavy (subcommand, loaded on use)

        try:
            settings = contact.parse_settings(args.contact) if args.contact else None
        except ValueError as exc:
            parser.error(str(exc))
        tasks = tuple(t.strip() for t in args.tasks.split(",")) if args.tasks else None
        print("comparing contact settings on the grasping experts...", file=sys.stderr)
        result = contact.run(
            settings or contact.DEFAULT_SETTINGS,
            tasks or contact.DEFAULT_TASKS,
            episodes=args.episodes,
        )
        print(json.dumps(result, indent=2))
        return 0
    if args.benchmark == "latency":
        return _latency(args)
    if args.benchmark == "tracking":
        print("benchmarking motion-to-motion lag and tracking error...", file=sys.stderr)
        print(json.dumps(run_tracking(max_ticks=args.frames), indent=2))
        return 0
    if args.seconds is None:
        args.seconds = 5.0 if args.benchmark == "teleop" else 2.0
    samples: dict = {}
    if args.benchmark == "sim":
        from beavr_sim.bench.sim import run  # local: heavy (subcommand, loaded on use)

        print(f"benchmarking simulation ({args.seconds:g} s per measurement)...", file=sys.stderr)
        result = run(seconds=args.seconds, render_frames=args.frames or 20, samples=samples)
    elif args.benchmark == "retarget":
        from beavr_sim.bench.retarget import (
            run as run_retarget,  # local: heavy (subcommand, loaded on use)
        )

        print("benchmarking LEAP retargeting on the human hand trace...", file=sys.stderr)
        result = run_retarget(frames=args.frames, samples=samples)
    elif args.benchmark == "teleop":
        print("benchmarking the teleop pipeline on bundled VR traces...", file=sys.stderr)
        result = run_teleop(real_time_seconds=args.seconds, max_ticks=args.frames, samples=samples)
    elif args.benchmark == "view":
        print(
            f"benchmarking the browser view's cost to the loop ({args.seconds:g} s per run)...",
            file=sys.stderr,
        )
        result = run_view(seconds=args.seconds)
    elif args.benchmark == "hardware":
        print(
            "benchmarking hardware mirroring on emulated devices (pour trace, real time)...",
            file=sys.stderr,
        )
        result = run_hardware(samples=samples)
    if args.plot is not None and args.benchmark not in (
        "view",
        "hardware",
    ):  # view: no samples to plot
        result["plots"] = write_plots(args.benchmark, samples, args.plot, result)
        print(f"plots: {len(result['plots'])} PNG files in {args.plot}", file=sys.stderr)
    print(json.dumps(result, indent=2))
    return 0


def _latency(args) -> int:
    from beavr_sim.bench import latency  # local: heavy (subcommand, loaded on use)

    seconds = 10.0 if args.seconds is None else args.seconds
    samples: dict = {}
    if args.sweep or args.sweep_counts:
        counts = (
            [int(n) for n in args.sweep_counts.split(",")]
            if args.sweep_counts
            else list(latency.SWEEP_COUNTS)
        )
        if not args.json:
            print(
                f"benchmarking latency, sweep over {counts} effectors ({seconds:g} s each)...",
                file=sys.stderr,
            )
        result = latency.run_sweep(counts, seconds, mirror=not args.no_mirror, samples=samples)
        report = latency.sweep_table
    else:
        if not args.json:
            print(
                f"benchmarking latency, config {args.config}, {args.layout} ({seconds:g} s)...",
                file=sys.stderr,
            )
        result = latency.run(
            args.config, seconds, mirror=not args.no_mirror, samples=samples, layout=args.layout
        )
        report = latency.table
    if args.plot is not None:
        result["plots"] = [str(p) for p in write_latency(samples, args.plot, result)]
    if not args.json:
        print(report(result), file=sys.stderr)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
