"""The facts augmentation needs of a source that lost its episode log, recovered from what
LeRobot's own editing tools carry.

``lerobot-edit-dataset`` (delete_episodes, split, merge) writes a new dataset from the frames,
the per-episode task strings, ``info.json``'s features, fps and ``robot_type``, and its own
``meta/episodes`` columns: ``meta/beavr_episodes.jsonl`` and ``beavr_traces/`` are not copied.
Recovered per episode:

- **task**: its task string (the task's instruction, or its name when it has none) matched
  against the registered tasks;
- **embodiment**: ``info.json``'s ``robot_type`` (every beavr_sim writer sets it to the
  embodiment);
- **seed**: its first frame's ``observation.environment_state`` (object and fixture poses)
  matched against the task's resets at seeds ``0 .. RecoveryConfig.max_seed - 1``: the seed
  whose reset puts every thing within :attr:`RecoveryConfig.tolerance` of the recorded
  positions, nearest first. A source recorded without environment state
  (``--environment-state`` off, the default) has no seed in its frames: refused, with the
  reason. So is an episode no candidate seed matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from beavr_sim.datasets.features import ENV_STATE
from beavr_sim.datasets.shards import EPISODE_LOG
from beavr_sim.tasks.registry import TASKS, task_class


@dataclass(frozen=True)
class RecoveryConfig:
    max_seed: int = 10_000  # candidate seeds 0 .. max_seed - 1
    tolerance: float = 0.01  # m: largest position difference of a matching reset


@dataclass(frozen=True)
class Recovered:
    task: str
    embodiment: str
    seeds: dict[int, int]  # episode index -> seed


def task_of(text: str) -> str:
    """The registered task whose instruction (or name) is ``text``; raises naming them."""
    for name in TASKS:
        cls = task_class(name)
        if text in (cls.instruction, name):
            return name
    raise ValueError(f"task string {text!r} is no registered task's ({', '.join(TASKS)})")


def _positions(names: list[str]) -> np.ndarray:
    return np.array([i for i, n in enumerate(names) if n.rsplit("/", 1)[-1] in "xyz"], int)


def recover_seeds(
    task: str,
    embodiment: str,
    state_names: list[str],
    first_states: dict[int, np.ndarray],
    config: RecoveryConfig | None = None,
) -> dict[int, int]:
    """Episode index -> the seed whose reset matches its first environment state (see the
    module docstring); raises ValueError naming the episodes no candidate matched."""
    config = config or RecoveryConfig()
    env = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
    try:
        if list(env.environment_state_names) != list(state_names):
            raise ValueError(
                f"the recorded environment state ({len(state_names)} names) is not {task}'s"
            )
        cols = _positions(list(state_names))
        wanted = {e: np.asarray(s, np.float64)[cols] for e, s in first_states.items()}
        best: dict[int, tuple[float, int]] = {}
        for seed in range(config.max_seed):
            env.reset(seed=seed)
            here = np.asarray(env.environment_state, np.float64)[cols]
            for e, s in wanted.items():
                d = float(np.abs(here - s).max())
                if d <= config.tolerance and d < best.get(e, (np.inf, -1))[0]:
                    best[e] = (d, seed)
            if len(best) == len(wanted) and all(d < 1e-4 for d, _ in best.values()):
                break  # every episode matched exactly: no better seed is to be found
    finally:
        env.close()
    missing = sorted(set(wanted) - set(best))
    if missing:
        raise ValueError(
            f"no reset of {task} at seeds 0..{config.max_seed - 1} matches the first frame of "
            f"episodes {missing}"
        )
    return {e: seed for e, (_, seed) in best.items()}


def recover(root, info: dict) -> Recovered:
    """The task, embodiment and seeds of the source at ``root`` (its ``info.json`` parsed as
    ``info``) from its frames; raises ValueError saying what is missing."""
    import pandas as pd  # local: heavy

    lost = f"{root} has no {EPISODE_LOG} (LeRobot's editing tools drop it)"
    embodiment = info.get("robot_type")
    if not embodiment:
        raise ValueError(f"{lost} and its info.json names no robot_type (the embodiment)")
    if ENV_STATE not in info.get("features", {}):
        raise ValueError(
            f"{lost} and no {ENV_STATE} to recover the seeds from: record the source "
            "with --environment-state"
        )
    episodes = pd.concat(
        pd.read_parquet(f, columns=["episode_index", "tasks"])
        for f in sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    )
    texts = {str(t) for ts in episodes["tasks"] for t in ts}
    tasks = {task_of(t) for t in texts}
    if len(tasks) != 1:
        raise ValueError(f"{root} mixes tasks {sorted(tasks)}: one please")
    (task,) = tasks
    frames = pd.concat(
        pd.read_parquet(f, columns=[ENV_STATE, "episode_index", "frame_index"])
        for f in sorted((root / "data").glob("chunk-*/file-*.parquet"))
    )
    first = frames[frames["frame_index"] == 0]
    states = {
        int(e): np.asarray(s) for e, s in zip(first["episode_index"], first[ENV_STATE], strict=True)
    }
    names = info["features"][ENV_STATE]["names"]
    return Recovered(task, embodiment, recover_seeds(task, embodiment, names, states))
