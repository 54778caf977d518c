"""``python -m beavr_sim.bench scaling [--task T] [--episodes N] [--workers 1,2] [--ray]
[--image-size HxW] [--replay-only | --no-replay]``: JSON on the last line.

- ``generate``: the same ``python -m beavr_sim.datasets generate`` job (seeds 0..N-1) with each
  worker count in ``--workers`` (1 = in this process, the serial reference) and, with ``--ray``,
  on a local Ray cluster of the largest worker count. Wall time includes starting the workers
  and merging the shards; the Ray cluster itself is started before the timer, as a cluster is
  up before a job is submitted (its start is reported as ``cluster_start_s``). Reports
  speed-up against one worker, Ray's overhead against local workers of the same count,
  episodes per core-hour and what 1,000 episodes take.
- ``replay``: a headless replay of the task's bundled trace without cameras on the virtual
  clock (what every worker runs per episode, twice: synthesis and recording): ms per tick by
  stage, MuJoCo's own timers, and the speed against real time.

Every generation run writes into a fresh temporary folder, removed afterwards.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from beavr_sim.bench.timing import CallTimer
from beavr_sim.scaling.executors import ScaleConfig, connect_ray
from beavr_sim.tasks.registry import canonical_task_name

#: Stages timed in a replay tick: (label, attribute path from the loop, method).
STAGES = (
    ("source.poll", "source", "poll"),
    ("operator.observe", "operator", "observe"),
    ("operator.command", "operator", "command"),
    ("twin.command (step limit, guard)", "twin", "command"),
    ("twin.step (all)", "twin", "step"),
    ("task.evaluate", "twin.env.task", "evaluate"),
)


def _resolve(root, path: str):
    for part in path.split("."):
        root = getattr(root, part)
    return root


def replay_breakdown(task: str = "Pour") -> dict:
    """The bundled trace of ``task`` replayed headless, no cameras, virtual clock."""
    import mujoco

    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        SessionOptions,
        build_loop,
    )

    loop = build_loop(
        SessionOptions(task=task, source="trace", viser=False, headless=True, progress=False)
    )
    # Each stage's bound method, timed by the interpreter's monitoring (nothing replaced).
    stages = CallTimer(
        {label: getattr(_resolve(loop, path), method) for label, path, method in STAGES}
    )
    env = loop.twin.env
    data = env.data
    t0 = time.perf_counter()
    with stages:
        summary = loop.run()
    wall = time.perf_counter() - t0
    ticks = max(1, loop.ticks)
    timers = {}
    for name in ("STEP", "POSITION", "VELOCITY", "ACTUATION", "CONSTRAINT", "POS_COLLISION"):
        timer = data.timer[getattr(mujoco.mjtTimer, f"mjTIMER_{name}")]
        timers[name.lower()] = round(1e3 * timer.duration / ticks, 3)
    env.close()
    return {
        "task": task,
        "ticks": loop.ticks,
        "success": bool(summary.success),
        "control_hz": env.control_hz,
        "substeps_per_tick": env.n_substeps,
        "ms_per_tick": round(1e3 * wall / ticks, 3),
        "x_real_time": round(loop.ticks / env.control_hz / wall, 2),
        "ms_per_tick_by_stage": {
            k: round(1e3 * v / ticks, 3)
            for k, v in sorted(stages.totals.items(), key=lambda kv: -kv[1])
            if stages.calls[k]
        },
        "mujoco_ms_per_tick": timers,
    }


def _generate_once(task, episodes, out, config, scale) -> dict:
    from beavr_sim.synthetic.generate import generate  # local: heavy (mujoco)

    t0 = time.perf_counter()
    summary = generate(task, episodes, 0, out, config=config, progress=False, scale=scale)
    wall = time.perf_counter() - t0
    return {
        "backend": summary.backend,
        "workers": summary.workers,
        "episodes": summary.episodes_written,
        "frames": summary.frames,
        "wall_s": round(wall, 2),
    }


def generate_scaling(
    task: str, episodes: int, workers: list[int], ray: bool, image_size: tuple[int, int]
) -> dict:
    from beavr_sim.datasets.features import RecordingConfig  # local: heavy (mujoco)

    height, width = image_size
    config = RecordingConfig(cameras=("front",), image_height=height, image_width=width)
    runs = []
    with tempfile.TemporaryDirectory(prefix="beavr_bench_scaling_") as tmp:
        for n in workers:
            out = Path(tmp) / f"local{n}"
            print(f"generate: {episodes} episodes, {n} local worker(s)...", file=sys.stderr)
            runs.append(_generate_once(task, episodes, out, config, ScaleConfig(workers=n)))
            shutil.rmtree(out, ignore_errors=True)
        if ray:
            import ray as ray_module

            n = max(workers)
            # The cluster is up before the job, as on a real one (`ray start --head`): its
            # start is timed apart; the job's own workers start inside the job's time.
            t0 = time.perf_counter()
            connect_ray(None, n)
            ray_start_s = round(time.perf_counter() - t0, 2)
            print(f"generate: {episodes} episodes, Ray local cluster of {n}...", file=sys.stderr)
            out = Path(tmp) / "ray"
            try:
                run = _generate_once(task, episodes, out, config, ScaleConfig(n, ray=True))
            finally:
                ray_module.shutdown()
            run["cluster_start_s"] = ray_start_s
            runs.append(run)
    serial = next((r for r in runs if r["backend"] == "inline"), None)
    result: dict = {"task": task, "episodes": episodes, "image_size": list(image_size)}
    result["runs"] = runs
    if serial is not None:
        for r in runs:
            r["speedup_vs_1_worker"] = round(serial["wall_s"] / r["wall_s"], 2)
        per_episode = serial["wall_s"] / max(1, serial["episodes"])
        result["episodes_per_core_hour"] = round(3600.0 / per_episode, 1)
        result["core_hours_per_1000_episodes"] = round(1000 * per_episode / 3600.0, 2)
    local = {r["workers"]: r for r in runs if r["backend"] == "local"}
    ray_run = next((r for r in runs if r["backend"] == "ray"), None)
    if ray_run is not None and ray_run["workers"] in local:
        base = local[ray_run["workers"]]["wall_s"]
        result["ray_overhead_vs_local"] = round(ray_run["wall_s"] / base - 1.0, 3)
    best = min(runs, key=lambda r: r["wall_s"])
    result["hours_for_1000_episodes_here"] = round(
        best["wall_s"] / max(1, best["episodes"]) * 1000 / 3600.0, 2
    )
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m beavr_sim.bench scaling", description=__doc__)
    p.add_argument("--task", default="PickupBox")
    p.add_argument("--episodes", type=int, default=4, help="episodes per generation run")
    p.add_argument("--workers", default="1,2", help="comma-separated local worker counts")
    p.add_argument("--ray", action="store_true", help="also a local Ray cluster")
    p.add_argument("--image-size", default="96x128", help="HxW of the recorded front camera")
    p.add_argument("--replay-task", default="Pour", help="replay: the bundled trace's task")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--replay-only", action="store_true")
    group.add_argument("--no-replay", action="store_true")
    args = p.parse_args(argv)
    from beavr_sim.datasets.cli import parse_size  # local: heavy (mujoco)

    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        workers = [int(w) for w in args.workers.split(",") if w.strip()]
        if not workers or min(workers) < 1:
            raise ValueError(f"--workers takes counts >= 1, e.g. 1,2; got {args.workers!r}")
        size = parse_size(args.image_size)
        task = canonical_task_name(args.task)
        replay_task = canonical_task_name(args.replay_task)
    except ValueError as exc:
        p.error(str(exc))
    result: dict = {"cores": os.cpu_count(), "load_average": list(os.getloadavg())}
    if not args.no_replay:
        print(f"replay: {replay_task}'s bundled trace, headless...", file=sys.stderr)
        result["replay"] = replay_breakdown(replay_task)
    if not args.replay_only:
        result["generate"] = generate_scaling(task, args.episodes, workers, args.ray, size)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
