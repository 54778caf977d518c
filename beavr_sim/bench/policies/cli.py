"""``python -m beavr_sim.bench policies [--tasks T,...] [--policies act,diffusion] [--demos 50]
[--episodes 50] [--augment N] [--quick] [--out DIR] [--resume] [--device cpu|cuda] [--plot DIR]``:
the policy table.

Generates seeded demonstrations (and, with ``--augment N``, N episodes made from them by
``datasets augment``, trained on with them), trains each policy with ``lerobot-train``, chooses each run's
checkpoint on validation seeds, evaluates it on the test seeds (sync and think-act) beside the
scripted expert through the teleop pipeline, and writes ``DIR/table.md`` and
``DIR/table.json`` (also printed, last, as one JSON line); ``--plot PDIR`` adds a figure per
task (:mod:`beavr_sim.bench.policies.plot`). Every stage is cached in ``DIR`` by
its configuration: a re-run skips what is finished; ``--resume`` continues a training run cut
short from its last checkpoint. ``--quick``: 2 demos, 20 steps of a tiny ACT, 2 episodes of at
most 1 s, PickupBox (what the tests run). Seeds and stages: ``beavr_sim/bench/policies/``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from beavr_sim.bench.policies.config import EXTENDABLE_POLICIES, TRAINED_POLICIES, Protocol
from beavr_sim.bench.policies.stages import (
    RunOptions,
    StageFailed,
    Stages,
    TableConfig,
    run_table,
    stage_count,
)
from beavr_sim.bench.policies.table import write
from beavr_sim.bench.policies.train import TrainFailed, TrainUnfinished
from beavr_sim.datasets.cli import parse_cameras, parse_size
from beavr_sim.naming import UnknownNameError, check_name
from beavr_sim.scaling.executors import JobFailed
from beavr_sim.tasks.registry import canonical_task_name

LOOPS = ("sync", "async")


def _names(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m beavr_sim.bench policies",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--tasks", default=None, help="comma-separated (default PickupBox)")
    p.add_argument(
        "--policies",
        default=None,
        help=f"comma-separated, of {', '.join(TRAINED_POLICIES)} (default both; --quick: act)",
    )
    p.add_argument("--demos", type=int, default=None, help="demonstrations per task (50)")
    p.add_argument("--episodes", type=int, default=None, help="test episodes (50)")
    p.add_argument(
        "--validation-episodes", type=int, default=None, help="per checkpoint (20; --quick 2)"
    )
    p.add_argument(
        "--augment",
        type=int,
        default=0,
        help="also generate this many episodes from the demonstrations (datasets augment: "
        "their own motion in new scenes, no expert) and train on both (0: demos alone)",
    )
    p.add_argument("--steps", type=int, default=None, help="training steps (the preset's)")
    p.add_argument(
        "--save-freq", type=int, default=None, help="steps between checkpoints (the preset's)"
    )
    p.add_argument(
        "--cameras",
        default="none",
        help="cameras the policies see, e.g. front,overhead; none (default): joint state and "
        "the object poses",
    )
    p.add_argument("--image-size", default="96x128", help="HxW of the cameras (96x128)")
    p.add_argument(
        "--loops", default="sync,async", help="evaluation loops on the test seeds (sync,async)"
    )
    p.add_argument(
        "--max-seconds", type=float, default=None, help="evaluation episode limit (env's)"
    )
    p.add_argument("--embodiment", default="xarm7_leap_right")
    p.add_argument("--quick", action="store_true", help="the smoke-test sizes (see above)")
    p.add_argument("--out", type=Path, default=Path("outputs/policy_table"))
    p.add_argument("--resume", action="store_true", help="continue cut training runs")
    p.add_argument(
        "--extend",
        action="store_true",
        help="train to --steps by continuing the finished run of the same configuration with "
        "the most steps short of it (its checkpoints kept), not from step 0; "
        f"{', '.join(EXTENDABLE_POLICIES)} only (a constant learning rate)",
    )
    p.add_argument(
        "--plot",
        type=Path,
        default=None,
        metavar="DIR",
        help="also write one figure per task into DIR: training loss, success per checkpoint, "
        "the test results (PNG)",
    )
    p.add_argument("--device", default="cpu", help="torch device for training and evaluation")
    p.add_argument(
        "--eval-device",
        default=None,
        help="torch device for the evaluation episodes (default: --device); with a GPU, cpu "
        "often evaluates faster (each worker would set up CUDA)",
    )
    p.add_argument(
        "--workers", type=int, default=1, help="local processes for generation and evaluation"
    )
    p.add_argument(
        "--loader-workers",
        type=int,
        default=0,
        help="data-loading processes per training run (LeRobot's --num_workers; 0: in the "
        "training process, enough on a CPU, the bottleneck on a GPU)",
    )
    return p


def table_config(args: argparse.Namespace) -> TableConfig:
    """The :class:`TableConfig` of the options (``--quick`` fills what was not given)."""
    quick = args.quick
    tasks = _names(args.tasks) if args.tasks else ["PickupBox"]
    policies = (
        _names(args.policies) if args.policies else (["act"] if quick else ["act", "diffusion"])
    )
    for policy in policies:
        check_name("policy", policy, TRAINED_POLICIES)
    from beavr_sim.experts.base import check_expert_embodiment  # local: heavy (mujoco)

    check_expert_embodiment(args.embodiment)  # the demonstrations are the experts'
    loops = _names(args.loops)
    for loop in loops:
        check_name("loop", loop, LOOPS)
    if quick and not args.tasks:
        tasks = tasks[:1]
    small = 2 if quick else None
    episodes = args.episodes or small or 50
    cameras, depth = parse_cameras(args.cameras)
    if depth:
        raise ValueError("--cameras: the policies take RGB cameras only")
    height, width = parse_size(args.image_size)
    if args.augment < 0:
        raise ValueError(f"--augment must be >= 0 episodes, got {args.augment}")
    return TableConfig(
        tasks=tuple(dict.fromkeys(canonical_task_name(t) for t in tasks)),
        policies=tuple(dict.fromkeys(policies)),
        protocol=Protocol(
            demos=args.demos or small or 50,
            validation_episodes=args.validation_episodes or small or 20,
            test_episodes=episodes,
        ),
        quick=quick,
        embodiment=args.embodiment,
        cameras=cameras,
        image_height=height,
        image_width=width,
        steps=args.steps,
        save_freq=args.save_freq,
        max_seconds=args.max_seconds or (1.0 if quick else None),
        modes=tuple(dict.fromkeys(loops)),
        augment=args.augment,
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser().parse_args(argv)
    try:
        config = table_config(args)
        if args.extend:
            for policy in config.policies:
                # Diffusion's learning-rate schedule spans its total steps: no extending.
                check_name("policy", policy, EXTENDABLE_POLICIES, "for --extend")
        options = RunOptions(
            out=args.out,
            extend=args.extend,
            device=args.device,
            workers=args.workers,
            resume=args.resume,
            loader_workers=args.loader_workers,
            eval_device=args.eval_device,
        )
        if args.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {args.workers}")
        if args.loader_workers < 0:
            raise ValueError(f"--loader-workers must be >= 0, got {args.loader_workers}")
        stages = Stages(stage_count(config))
        result = run_table(config, options, stages)
    except (UnknownNameError, ValueError, FileNotFoundError, TrainFailed, TrainUnfinished,
            StageFailed, JobFailed) as exc:  # fmt: skip
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.plot is not None:
        from beavr_sim.bench.policies import plot  # local: heavy (matplotlib)

        result["plots"] = [str(p) for p in plot.write(result, args.plot)]
    command = "python -m beavr_sim.bench policies " + shlex.join(argv)
    md, js = write(result, args.out, command.strip())
    print(f"table: {md} and {js}", file=sys.stderr)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
