"""``python -m beavr_sim.eval.fit --policy PATH --dataset DIR [--episodes 0 1] [--device cpu]``

Open-loop fit: a policy fed a recorded episode's observations, frame by frame, as it would be
fed the env's (its own action queue and observation history included), and its actions set
against the recorded ones. On the episodes it was trained on this separates a policy that
never learned its data from one that learned it and drifts once its own actions move the
scene: a policy that cannot reproduce its training episodes will not succeed in the env, and
more evaluation will not say why.

Prints one JSON line: per episode and over all, the mean absolute action error in the
action's units (rad for joints), the same per action dimension (named as the dataset names
them), and ``relative``: that error over the recorded actions' standard deviation (0: exact;
about 1: no better than a constant).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beavr_sim.eval.policy import IMAGE_PREFIX, LoadedPolicy

STATE = "observation.state"
ENV_STATE = "observation.environment_state"


@dataclass(frozen=True)
class Fit:
    """Open-loop action error of one policy on some recorded episodes."""

    episodes: tuple[int, ...]
    frames: int
    mean_abs: float
    relative: float  # mean over dimensions of (mean |error| / std of the recorded action)
    per_dimension: dict[str, float]
    per_episode: dict[int, float]

    def as_dict(self) -> dict:
        return {
            "episodes": list(self.episodes),
            "frames": self.frames,
            "mean_abs": round(self.mean_abs, 5),
            "relative": round(self.relative, 4),
            "per_dimension": {k: round(v, 5) for k, v in self.per_dimension.items()},
            "per_episode": {str(k): round(v, 5) for k, v in self.per_episode.items()},
        }

    def describe(self) -> str:
        worst = max(self.per_dimension, key=self.per_dimension.__getitem__)
        return (
            f"open-loop fit on {self.frames} recorded frames (episodes "
            f"{', '.join(map(str, self.episodes))}): mean |action error| {self.mean_abs:.4f}, "
            f"{self.relative:.2f} of the actions' spread; worst {worst} "
            f"{self.per_dimension[worst]:.4f}"
        )


def env_observation(frame: dict) -> dict:
    """A dataset frame as the env's observation (what :class:`LoadedPolicy` takes)."""
    obs: dict = {"agent_pos": np.asarray(frame[STATE], dtype=np.float32)}
    if ENV_STATE in frame:
        obs["environment_state"] = np.asarray(frame[ENV_STATE], dtype=np.float32)
    pixels = {}
    for key, value in frame.items():
        if key.startswith(IMAGE_PREFIX):
            chw = np.asarray(value, dtype=np.float32)  # LeRobot gives C x H x W in [0, 1]
            pixels[key.removeprefix(IMAGE_PREFIX)] = np.ascontiguousarray(
                np.clip(np.rint(chw * 255.0), 0, 255).astype(np.uint8).transpose(1, 2, 0)
            )
    if pixels:
        obs["pixels"] = pixels
    return obs


def open_loop_fit(
    policy: LoadedPolicy, dataset, episodes: tuple[int, ...], progress: bool = False
) -> Fit:
    """The policy's actions on ``episodes`` of ``dataset`` (a LeRobotDataset) against the
    recorded ones."""
    n = int(dataset.meta.total_episodes)
    bad = [e for e in episodes if not 0 <= e < n]
    if bad:
        raise ValueError(f"episodes {bad} are not in the dataset (it holds 0..{n - 1})")
    if not episodes:
        raise ValueError("no episode to fit: pass at least one")
    names = list(dataset.meta.features["action"].get("names") or [])
    errors, recorded, per_episode = [], [], {}
    total = sum(
        int(dataset.meta.episodes[e]["dataset_to_index"])
        - int(dataset.meta.episodes[e]["dataset_from_index"])
        for e in episodes
    )
    from tqdm import tqdm

    bar = tqdm(total=total, desc="fit", unit="frame", disable=not progress, file=sys.stderr)
    for episode in episodes:
        meta = dataset.meta.episodes[episode]
        lo, hi = int(meta["dataset_from_index"]), int(meta["dataset_to_index"])
        policy.reset()
        task = ""
        episode_errors = []
        for index in range(lo, hi):
            frame = dataset[index]
            task = frame.get("task", task)
            action = policy.act(env_observation(frame), task)
            truth = np.asarray(frame["action"], dtype=np.float64)
            episode_errors.append(np.abs(action - truth))
            recorded.append(truth)
            bar.update()
        per_episode[episode] = float(np.mean(episode_errors))
        errors.extend(episode_errors)
    bar.close()
    err = np.asarray(errors)
    spread = np.asarray(recorded).std(axis=0)
    mean_per_dim = err.mean(axis=0)
    moving = spread > 1e-9  # a dimension the recordings never move says nothing relative
    relative = float(np.mean(mean_per_dim[moving] / spread[moving])) if moving.any() else 0.0
    if len(names) != err.shape[1]:
        names = [f"action_{i}" for i in range(err.shape[1])]
    return Fit(
        episodes=tuple(episodes),
        frames=int(err.shape[0]),
        mean_abs=float(err.mean()),
        relative=relative,
        per_dimension=dict(zip(names, map(float, mean_per_dim), strict=True)),
        per_episode=per_episode,
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m beavr_sim.eval.fit",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--policy", type=Path, required=True, help="a pretrained_model folder")
    p.add_argument("--dataset", type=Path, required=True, help="a LeRobot dataset folder")
    p.add_argument(
        "--episodes", type=int, nargs="+", default=[0], help="episode indices (default: 0)"
    )
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    args = p.parse_args(argv)
    from beavr_sim.datasets.writer import open_dataset  # local: heavy (LeRobot datasets)

    try:
        policy = LoadedPolicy(args.policy, device=args.device)
        dataset = open_dataset(args.dataset)
        fit = open_loop_fit(policy, dataset, tuple(args.episodes), progress=not args.quiet)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(fit.describe(), file=sys.stderr)
    print(json.dumps({"policy_path": str(args.policy), **fit.as_dict()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
