"""Running a policy in a beavr_sim env: synchronously, or in BEAVR's think-act loop.

- sync: every control tick, observe then ``act`` then step (inference time stalls the clock;
  the simulation does not care, a real robot would).
- async (``ThinkAct``): a fixed-rate control loop in real time steps the env from an action
  queue while an inference thread refills the queue with action chunks computed from the
  newest observation. Actions whose time passed while the chunk was computed are dropped, so
  the robot follows the chunk from "now". A tick that finds the queue empty holds the last
  action and is counted (``ticks_without_action``); the loop's period error is the jitter.
  A policy with a ``history`` > 1 (Diffusion's ``n_obs_steps``) is observed every tick and
  handed its last ``history`` observations.

The control thread alone touches MuJoCo (env, renderer); the inference thread sees copies.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from beavr_sim.datasets.recorder import CameraSet
from beavr_sim.robots.identity import robot_identity
from beavr_sim.scaling.stats import wilson_interval


@dataclass
class EpisodeResult:
    seed: int
    success: bool
    seconds: float
    ticks: int
    ticks_without_action: int = 0
    periods_ms: list[float] = field(default_factory=list)
    #: The task checker's conditions at the episode's end (``lifted``, ``in_area``, ...):
    #: what a failed episode lacked.
    final: dict[str, bool] = field(default_factory=dict)


def checker_conditions(info: dict) -> dict[str, bool]:
    """The task checker's true/false conditions in an env step's ``info`` (``task/*``)."""
    return {
        key.removeprefix("task/"): bool(value)
        for key, value in info.items()
        if key.startswith("task/") and isinstance(value, bool | np.bool_)
    }


def _observation(env, cameras: CameraSet) -> dict:
    obs = {"agent_pos": env.agent_pos.copy()}
    if env.environment_state_names:
        obs["environment_state"] = env.environment_state
    pixels = cameras.render_env(env)
    if pixels:
        obs["pixels"] = pixels
    return obs


class _VideoWriter:
    def __init__(self, path: Path | None, env, fps: float):
        self.path = path
        self._frames: list[np.ndarray] = []
        self._env = env
        self._fps = fps
        self._camera = CameraSet.of_env(env, ("front",), 240, 320) if path else None

    def capture(self) -> None:
        if self._camera is not None:
            self._frames.append(self._camera.render_env(self._env)["front"])

    def close(self) -> None:
        if self._camera is None:
            return
        self._camera.close()
        if self._frames:
            import imageio.v2 as imageio

            self.path.parent.mkdir(parents=True, exist_ok=True)
            imageio.mimwrite(self.path, self._frames, fps=self._fps, macro_block_size=1)


def run_sync(env, policy, cameras: CameraSet, seed: int, max_seconds: float, video=None):
    env.reset(seed=seed)
    policy.reset()
    task = env.task.instruction or env.task.name
    ticks, success = 0, False
    while True:
        action = policy.act(_observation(env, cameras), task)
        _, _, terminated, truncated, info = env.step(action.astype(np.float32))
        ticks += 1
        if video is not None:
            video.capture()
        success = success or bool(info["is_success"])
        if terminated or truncated or ticks / env.control_hz >= max_seconds:
            break
    return EpisodeResult(
        seed, success, ticks / env.control_hz, ticks, final=checker_conditions(info)
    )


class ThinkAct:
    """The async think-act loop of one episode (see the module docstring)."""

    def __init__(self, env, policy, cameras: CameraSet, refill_at: int = 0):
        self.env = env
        self.policy = policy
        self.cameras = cameras
        self.refill_at = int(refill_at)
        self._request: tuple[int, dict] | None = None
        self._result: tuple[int, np.ndarray] | None = None
        self._error: BaseException | None = None
        self._cv = threading.Condition()
        self._stop = False

    def _think(self, task: str) -> None:
        while True:
            with self._cv:
                while self._request is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                tick, obs = self._request
                self._request = None
            try:
                chunk = self.policy.chunk(obs, task)
            except BaseException as exc:  # reported by the control loop
                with self._cv:
                    self._error = exc
                return
            with self._cv:
                self._result = (tick, chunk)

    def run(self, seed: int, max_seconds: float, video=None) -> EpisodeResult:
        env = self.env
        env.reset(seed=seed)
        self.policy.reset()
        task = env.task.instruction or env.task.name
        dt = 1.0 / env.control_hz
        thinker = threading.Thread(target=self._think, args=(task,), daemon=True)
        thinker.start()
        queue: deque[np.ndarray] = deque()
        recent: deque[dict] = deque(maxlen=int(getattr(self.policy, "history", 1)))
        last_action = env.agent_pos.astype(np.float64)
        thinking = False
        result = EpisodeResult(seed, False, 0.0, 0)
        t0 = time.perf_counter()
        t_prev = None
        try:
            while True:
                now = time.perf_counter()
                if t_prev is not None:
                    result.periods_ms.append((now - t_prev) * 1e3)
                t_prev = now
                if recent.maxlen > 1:
                    recent.append(_observation(env, self.cameras))
                with self._cv:
                    if self._error is not None:
                        raise RuntimeError("policy inference failed") from self._error
                    if self._result is not None:
                        tick_obs, chunk = self._result
                        self._result = None
                        thinking = False
                        late = result.ticks - tick_obs  # actions already due while thinking
                        queue = deque(chunk[late:])
                    if not thinking and len(queue) <= self.refill_at:
                        observed = list(recent) if recent.maxlen > 1 else None
                        self._request = (result.ticks, observed or _observation(env, self.cameras))
                        thinking = True
                        self._cv.notify()
                if queue:
                    last_action = queue.popleft()
                else:
                    result.ticks_without_action += 1
                _, _, terminated, truncated, info = env.step(last_action.astype(np.float32))
                result.ticks += 1
                if video is not None:
                    video.capture()
                result.success = result.success or bool(info["is_success"])
                if terminated or truncated or result.ticks * dt >= max_seconds:
                    result.final = checker_conditions(info)
                    break
                delay = t0 + result.ticks * dt - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
        finally:
            with self._cv:
                self._stop = True
                self._cv.notify()
            thinker.join(timeout=10.0)
            self._stop = False
            self._request = self._result = None
        result.seconds = result.ticks * dt
        return result


def evaluate(
    policy,
    task: str,
    embodiment: str,
    episodes: int,
    seed: int,
    asynchronous: bool = False,
    max_seconds: float | None = None,
    videos: Path | None = None,
    progress: bool = True,
) -> dict:
    """Run ``episodes`` episodes (seeds ``seed``, ``seed+1``, ...); the summary dict."""
    from tqdm import tqdm

    env = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
    if env.action_space.shape[0] != policy.action_dim:
        raise ValueError(
            f"the policy outputs {policy.action_dim} joint targets; {embodiment} takes "
            f"{env.action_space.shape[0]}"
        )
    sizes = set(policy.cameras.values())
    if len(sizes) > 1:
        raise ValueError(f"the policy's cameras differ in size: {policy.cameras}")
    height, width = sizes.pop() if sizes else (1, 1)
    cameras = CameraSet.of_env(env, tuple(policy.cameras), height, width)
    limit = max_seconds or env.max_episode_seconds
    results: list[EpisodeResult] = []
    think_act = ThinkAct(env, policy, cameras) if asynchronous else None
    try:
        for i in tqdm(range(episodes), desc=f"eval {task}", unit="ep", disable=not progress):
            video = None
            if videos is not None:
                video = _VideoWriter(
                    Path(videos) / f"{task.lower()}_seed{seed + i:05d}.mp4", env, env.control_hz
                )
            try:
                if think_act is not None:
                    results.append(think_act.run(seed + i, limit, video))
                else:
                    results.append(run_sync(env, policy, cameras, seed + i, limit, video))
            finally:
                if video is not None:
                    video.close()
    finally:
        cameras.close()
        env.close()
    return summarize(results, task, embodiment, policy.type, asynchronous, env.control_hz)


def summarize(
    results: list[EpisodeResult],
    task: str,
    embodiment: str,
    policy_type: str,
    asynchronous: bool,
    control_hz: float,
) -> dict:
    """The summary of one (policy, task): success rate with its Wilson 95 % interval, mean
    episode time (and over the successful episodes, the mean time to success), how many failed
    episodes ended without each of the checker's conditions (``unmet_at_end``, most first) and
    each episode's seed, outcome, length and end conditions (``per_episode``); with
    ``asynchronous`` the control loop's jitter and starved ticks."""
    successes = sum(r.success for r in results)
    low, high = wilson_interval(successes, len(results))
    success_times = [r.seconds for r in results if r.success]
    robot = robot_identity(embodiment)
    summary = {
        "task": task,
        "embodiment": robot.name,
        "policy": policy_type,
        "episodes": len(results),
        "successes": successes,
        "success_rate": successes / len(results),
        "success_ci95": [round(low, 4), round(high, 4)],
        "mean_time_s": round(float(np.mean([r.seconds for r in results])), 3),
        # An episode ends at success: its length is the time to success (None: no success).
        "mean_success_time_s": (round(float(np.mean(success_times)), 3) if success_times else None),
        "mode": "async" if asynchronous else "sync",
        "unmet_at_end": unmet_at_end(results),
        "per_episode": [
            {"seed": r.seed, "success": r.success, "seconds": round(r.seconds, 3), "final": r.final}
            for r in results
        ],
    }
    if robot.is_file:  # which file: its label alone does not say
        summary["robot_file"] = {"path": robot.path, "sha256": robot.sha256}
    if asynchronous:
        periods = np.array([p for r in results for p in r.periods_ms])
        dt_ms = 1e3 / control_hz
        error = np.abs(periods - dt_ms) if periods.size else np.zeros(1)
        summary["control_jitter_ms"] = {
            "p50": round(float(np.percentile(error, 50)), 3),
            "p99": round(float(np.percentile(error, 99)), 3),
            "max": round(float(error.max()), 3),
        }
        summary["ticks_without_action"] = int(sum(r.ticks_without_action for r in results))
        summary["ticks"] = int(sum(r.ticks for r in results))
    return summary


def unmet_at_end(results: list[EpisodeResult]) -> dict[str, int]:
    """Per checker condition, the failed episodes that ended without it, most first (an
    episode lacking two counts in both)."""
    counts: dict[str, int] = {}
    for r in results:
        if not r.success:
            for name, met in r.final.items():
                if not met:
                    counts[name] = counts.get(name, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))
