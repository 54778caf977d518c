"""Evaluation sweeps: several policies x several tasks, episodes run by local workers or Ray.

Every episode is a job (:class:`EvalJob`: policy folder, task, seed); a worker keeps the policies
and envs it loaded for the next jobs. Each (policy, task) pair runs the same seeds (``seed``,
``seed + 1``, ...), so the policies are compared on the same initial states. The result is one
row per pair (:func:`beavr_sim.eval.runner.summarize`: success rate with its Wilson 95 %
interval, mean episode time), written as CSV or markdown by :func:`write_table`.
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym

from beavr_sim.datasets.recorder import CameraSet
from beavr_sim.eval.policy import LoadedPolicy
from beavr_sim.eval.runner import EpisodeResult, ThinkAct, _VideoWriter, run_sync, summarize
from beavr_sim.scaling.executors import ScaleConfig, make_executor

#: Columns of the table files, in order.
COLUMNS = (
    "policy_path",
    "policy",
    "task",
    "episodes",
    "successes",
    "success_rate",
    "ci95_low",
    "ci95_high",
    "mean_time_s",
    "mode",
)


@dataclass(frozen=True)
class EvalJob:
    policy: str  # pretrained_model folder
    task: str
    embodiment: str
    seed: int
    asynchronous: bool = False
    max_seconds: float | None = None
    video: str | None = None
    device: str = "cpu"


@dataclass(frozen=True)
class EvalEpisode:
    job: EvalJob
    result: EpisodeResult
    policy_type: str
    control_hz: float


def policy_spec(path: str | Path) -> tuple[str, int, dict[str, tuple[int, int]]]:
    """(type, action size, {camera: (height, width)}) of a pretrained policy folder, from its
    ``config.json`` alone (no torch), to check a sweep before any worker starts."""
    path = Path(path)
    config_file = path / "config.json"
    if not config_file.is_file():
        raise FileNotFoundError(
            f"{path} is not a LeRobot pretrained policy folder (no config.json); pass e.g. "
            "outputs/train/<run>/checkpoints/last/pretrained_model"
        )
    config = json.loads(config_file.read_text())
    prefix = "observation.images."
    cameras = {
        key.removeprefix(prefix): (int(ft["shape"][1]), int(ft["shape"][2]))
        for key, ft in config.get("input_features", {}).items()
        if key.startswith(prefix)
    }
    action = config.get("output_features", {}).get("action", {}).get("shape", [0])
    return str(config.get("type", "?")), int(action[0]), cameras


def check_sweep(policies: Sequence[Path], tasks: Sequence[str], embodiment: str) -> None:
    """Every policy runs on every task's env: action sizes and camera sizes agree."""
    specs = {str(p): policy_spec(p) for p in policies}
    for task in tasks:
        env = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
        try:
            action_dim = env.action_space.shape[0]
        finally:
            env.close()
        for path, (_, dim, cameras) in specs.items():
            if dim != action_dim:
                raise ValueError(
                    f"the policy {path} outputs {dim} joint targets; {embodiment} takes "
                    f"{action_dim}"
                )
            if len(set(cameras.values())) > 1:
                raise ValueError(f"the policy {path}'s cameras differ in size: {cameras}")


# Per worker process: what earlier jobs loaded.
_POLICIES: dict[tuple[str, str], object] = {}
_ENVS: dict[tuple, tuple[object, object]] = {}


def run_eval_job(job: EvalJob) -> EvalEpisode:
    """Worker entry: one episode (the policy and env are loaded once per worker)."""
    policy = _POLICIES.get((job.policy, job.device))
    if policy is None:
        policy = _POLICIES[(job.policy, job.device)] = LoadedPolicy(job.policy, job.device)
    sizes = set(policy.cameras.values())
    height, width = sizes.pop() if sizes else (1, 1)
    env_key = (job.task, job.embodiment, tuple(policy.cameras), height, width)
    if env_key not in _ENVS:
        env = gym.make(f"beavr_sim/{job.task}-v0", embodiment=job.embodiment).unwrapped
        _ENVS[env_key] = (env, CameraSet.of_env(env, tuple(policy.cameras), height, width))
    env, cameras = _ENVS[env_key]
    limit = job.max_seconds or env.max_episode_seconds
    video = _VideoWriter(Path(job.video), env, env.control_hz) if job.video else None
    try:
        if job.asynchronous:
            result = ThinkAct(env, policy, cameras).run(job.seed, limit, video)
        else:
            result = run_sync(env, policy, cameras, job.seed, limit, video)
    finally:
        if video is not None:
            video.close()
    return EvalEpisode(job, result, policy.type, float(env.control_hz))


def sweep(
    policies: Sequence[Path],
    tasks: Sequence[str],
    embodiment: str,
    episodes: int,
    seed: int,
    scale: ScaleConfig | None = None,
    asynchronous: bool = False,
    max_seconds: float | None = None,
    videos: Path | None = None,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Every policy on every task for ``episodes`` seeds. Returns ``{"results": [row per
    (policy, task), in the order given], "backend", "workers", "episodes_total", "wall_s"}``."""
    from tqdm import tqdm

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not policies or not tasks:
        raise ValueError("a sweep needs at least one policy and one task")
    scale = scale or ScaleConfig(workers=1)
    check_sweep(policies, tasks, embodiment)
    jobs: list[EvalJob] = []
    for i, policy in enumerate(policies):
        for task in tasks:
            for k in range(episodes):
                video = None
                if videos is not None:
                    prefix = f"policy{i}_" if len(policies) > 1 else ""
                    video = str(Path(videos) / f"{prefix}{task.lower()}_seed{seed + k:05d}.mp4")
                jobs.append(
                    EvalJob(
                        policy=str(policy),
                        task=task,
                        embodiment=embodiment,
                        seed=seed + k,
                        asynchronous=asynchronous,
                        max_seconds=max_seconds,
                        video=video,
                        device=device,
                    )
                )
    start = time.perf_counter()
    executor = make_executor("beavr_sim.eval.sweep:run_eval_job", scale)
    done: dict[int, EvalEpisode] = {}
    bar = tqdm(total=len(jobs), desc="eval", unit="ep", disable=not progress)
    try:
        for index, job in enumerate(jobs):
            executor.submit(index, job)
        while len(done) < len(jobs):
            index, episode = executor.next_result()
            done[index] = episode
            bar.update(1)
            bar.set_postfix(ok=sum(e.result.success for e in done.values()))
        workers = executor.capacity
    finally:
        executor.close()
        bar.close()
    rows = []
    for policy in policies:
        for task in tasks:
            mine = [
                done[i]
                for i, job in enumerate(jobs)
                if job.policy == str(policy) and job.task == task
            ]
            mine.sort(key=lambda e: e.job.seed)
            row = summarize(
                [e.result for e in mine],
                task,
                embodiment,
                mine[0].policy_type,
                asynchronous,
                mine[0].control_hz,
            )
            rows.append({"policy_path": str(policy), **row})
    return {
        "results": rows,
        "backend": scale.backend,
        "workers": workers,
        "episodes_total": len(jobs),
        "wall_s": round(time.perf_counter() - start, 2),
    }


def table_rows(rows: Sequence[dict]) -> list[dict]:
    return [
        {
            **{k: row[k] for k in COLUMNS if k in row},
            "ci95_low": row["success_ci95"][0],
            "ci95_high": row["success_ci95"][1],
        }
        for row in rows
    ]


def write_table(rows: Sequence[dict], path: Path) -> Path:
    """The sweep's rows as CSV (``.csv``) or a markdown table (``.md``)."""
    path = Path(path)
    flat = table_rows(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".csv":
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(COLUMNS))
            writer.writeheader()
            writer.writerows(flat)
    elif path.suffix == ".md":
        lines = [
            "| " + " | ".join(COLUMNS) + " |",
            "|" + "---|" * len(COLUMNS),
            *("| " + " | ".join(str(r[c]) for c in COLUMNS) + " |" for r in flat),
        ]
        path.write_text("\n".join(lines) + "\n")
    else:
        raise ValueError(f"a table file ends in .csv or .md, got {path.name!r}")
    return path
