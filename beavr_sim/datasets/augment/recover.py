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
- **seed**, with ``observation.environment_state`` (recorded with ``--environment-state``):
  its first frame (object and fixture poses) matched against the task's resets at the
  candidate seeds (:attr:`RecoveryConfig.seeds`): the seed whose reset puts every thing within
  :attr:`RecoveryConfig.tolerance` of the recorded positions, nearest first;
- **seed**, without it (the default recording): the first candidate seed whose reset, with
  the episode's recorded actions replayed on it, gives back its ``observation.state`` frame by
  frame (:mod:`.replay_match`).

Refused in one line, naming what is missing and how to record it: no ``robot_type``, no
``observation.state`` either, an episode no candidate seed matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from beavr_sim.datasets.augment.replay_match import MatchConfig, Recorded, match_seeds
from beavr_sim.datasets.features import ACTION, ENV_STATE, STATE
from beavr_sim.datasets.robot_meta import dataset_embodiment
from beavr_sim.datasets.shards import EPISODE_LOG
from beavr_sim.tasks.registry import TASKS, task_class


@dataclass(frozen=True)
class RecoveryConfig:
    seeds: range = range(10_000)  # candidate seeds, tried in order
    tolerance: float = 0.01  # m: largest position difference of a matching reset
    joint_tolerance: float = 1e-3  # rad: largest joint difference of a reproduced frame


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
        for seed in config.seeds:
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
            f"no reset of {task} at seeds {config.seeds.start}..{config.seeds.stop - 1} matches "
            f"the first frame of episodes {missing}"
        )
    return {e: seed for e, (_, seed) in best.items()}


def _frames(root, columns: list[str]):
    import pandas as pd  # local: heavy

    return pd.concat(
        pd.read_parquet(f, columns=[*columns, "episode_index", "frame_index"])
        for f in sorted((root / "data").glob("chunk-*/file-*.parquet"))
    ).sort_values(["episode_index", "frame_index"])


def _task(root) -> str:
    import pandas as pd  # local: heavy

    episodes = pd.concat(
        pd.read_parquet(f, columns=["episode_index", "tasks"])
        for f in sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    )
    tasks = {task_of(str(t)) for ts in episodes["tasks"] for t in ts}
    if len(tasks) != 1:
        raise ValueError(f"{root} mixes tasks {sorted(tasks)}: one please")
    (task,) = tasks
    return task


def replayed_seeds(
    root, task: str, embodiment: str, config: RecoveryConfig | None = None
) -> dict[int, int]:
    """Episode index -> seed, by replaying each episode's actions at the candidate seeds
    (:mod:`.replay_match`); raises ValueError naming the episodes none reproduced and why."""
    config = config or RecoveryConfig()
    frames = _frames(root, [ACTION, STATE])
    episodes = {
        int(e): Recorded(
            np.stack(g[ACTION].to_numpy()).astype(np.float64),
            np.stack(g[STATE].to_numpy()).astype(np.float64),
        )
        for e, g in frames.groupby("episode_index")
    }
    env = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
    try:
        found, why = match_seeds(env, episodes, MatchConfig(config.seeds, config.joint_tolerance))
    finally:
        env.close()
    if why:
        lines = "; ".join(f"episode {e}: {w}" for e, w in sorted(why.items()))
        raise ValueError(f"{lines} (no {ENV_STATE} recorded to match instead)")
    return found


def recover(root, info: dict, config: RecoveryConfig | None = None) -> Recovered:
    """The task, embodiment and seeds of the source at ``root`` (its ``info.json`` parsed as
    ``info``) from its frames; raises ValueError in one line saying what is missing."""
    lost = f"{root} has no {EPISODE_LOG} (LeRobot's editing tools drop it)"
    record = f"record the source with --environment-state, or keep its {EPISODE_LOG}"
    embodiment = info.get("robot_type")
    if not embodiment:
        raise ValueError(f"{lost} and its info.json names no robot_type (the embodiment)")
    embodiment = dataset_embodiment(root, embodiment)
    features = info.get("features", {})
    if ENV_STATE not in features and STATE not in features:
        raise ValueError(f"{lost}, no {ENV_STATE} and no {STATE} to find the seeds from: {record}")
    task = _task(root)
    if ENV_STATE not in features:
        try:
            return Recovered(task, embodiment, replayed_seeds(root, task, embodiment, config))
        except ValueError as exc:
            raise ValueError(f"{lost}: {exc}: {record}") from None
    frames = _frames(root, [ENV_STATE])
    first = frames[frames["frame_index"] == 0]
    states = {
        int(e): np.asarray(s) for e, s in zip(first["episode_index"], first[ENV_STATE], strict=True)
    }
    names = features[ENV_STATE]["names"]
    return Recovered(task, embodiment, recover_seeds(task, embodiment, names, states, config))
