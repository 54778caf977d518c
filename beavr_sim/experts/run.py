"""Run a scripted expert for episodes of a task and measure its success rate."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
from tqdm import tqdm

from beavr_sim.envs.registration import env_id
from beavr_sim.experts.registry import expert_class


@dataclass(frozen=True)
class EpisodeResult:
    seed: int
    success: bool
    seconds: float
    details: dict


@dataclass(frozen=True)
class ExpertReport:
    task: str
    embodiment: str
    episodes: int
    successes: int
    success_rate: float
    mean_time_s: float | None

    def to_json(self) -> str:
        return json.dumps(asdict(self))


def run_episode(env, expert, seed: int, frames: list | None = None) -> EpisodeResult:
    """One episode from ``env.reset(seed=seed)`` until terminated or truncated."""
    env.reset(seed=seed)
    expert.reset()
    info: dict = {}
    terminated = truncated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(expert.act())
        if frames is not None:
            frames.append(env.render())
    details = {k.removeprefix("task/"): v for k, v in info.items() if k.startswith("task/")}
    return EpisodeResult(seed, bool(info["is_success"]), float(info["elapsed_seconds"]), details)


def run_expert(
    task: str,
    embodiment: str,
    episodes: int,
    seed: int = 0,
    render_dir: Path | None = None,
    progress: bool = True,
) -> tuple[ExpertReport, list[EpisodeResult]]:
    """Episodes with seeds ``seed .. seed + episodes - 1``; optionally one video per episode."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    kwargs = {"embodiment": embodiment}
    if render_dir is not None:
        kwargs.update(render_mode="rgb_array", camera_height=240, camera_width=320)
        render_dir.mkdir(parents=True, exist_ok=True)
    env = gym.make(env_id(task), **kwargs).unwrapped
    expert = expert_class(task)(env)
    results = []
    bar = tqdm(range(seed, seed + episodes), desc=f"{task} / {embodiment}", disable=not progress)
    for s in bar:
        frames: list | None = [] if render_dir is not None else None
        result = run_episode(env, expert, s, frames)
        results.append(result)
        bar.set_postfix(success=f"{sum(r.success for r in results)}/{len(results)}")
        if frames:
            _save_video(render_dir / f"{task}_{embodiment}_seed{s}.mp4", frames, env.control_hz)
    env.close()
    times = [r.seconds for r in results if r.success]
    successes = sum(r.success for r in results)
    report = ExpertReport(
        task=task,
        embodiment=embodiment,
        episodes=episodes,
        successes=successes,
        success_rate=successes / episodes,
        mean_time_s=float(np.mean(times)) if times else None,
    )
    return report, results


def _save_video(path: Path, frames: list, fps: float) -> None:
    """An H.264 mp4 (imageio's bundled ffmpeg)."""
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(frames), fps=fps, codec="libx264")
