"""A source dataset for augmentation: its episodes (seed, task, embodiment, actions) and the
recording options that reproduce its features.

Reads ``meta/info.json``, ``meta/beavr_episodes.jsonl`` (kept episodes, by episode index)
and the action column of ``data/``. A dataset without the episode log (one edited with
LeRobot's tools drops it) has its task, embodiment and seeds recovered from what those tools
carry (:mod:`.recover`), or is refused with the reason.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from beavr_sim.datasets.augment.recover import recover
from beavr_sim.datasets.features import ACTION, ENV_STATE, IMAGE_PREFIX, KEYPOINTS, RecordingConfig
from beavr_sim.datasets.robot_meta import dataset_embodiment
from beavr_sim.datasets.save_journal import undo_interrupted_save
from beavr_sim.datasets.shards import EPISODE_LOG, read_log
from beavr_sim.datasets.writer import dataset_exists


@dataclass(frozen=True)
class SourceEpisode:
    """One recorded episode: its index in the source, the seed of its reset, the actions."""

    index: int
    seed: int
    task: str
    embodiment: str
    actions: np.ndarray  # (frames, joints), float32: what the twin was given


@dataclass(frozen=True)
class Source:
    root: Path
    task: str
    embodiment: str
    fps: int
    episodes: tuple[int, ...]  # episode indices of kept episodes with a seed
    seeds: tuple[int, ...]
    features: dict

    def recording_config(self, cameras: tuple[str, ...] | None = None) -> RecordingConfig:
        """The options that record this source's features (``cameras`` replaces its own)."""
        own = tuple(
            k.removeprefix(IMAGE_PREFIX) for k in self.features if k.startswith(IMAGE_PREFIX)
        )
        height, width = 480, 640
        for key in self.features:
            if key.startswith(IMAGE_PREFIX):
                height, width = self.features[key]["shape"][:2]
                break
        videos = any(f["dtype"] == "video" for f in self.features.values())
        return RecordingConfig(
            fps=self.fps,
            cameras=own if cameras is None else cameras,
            image_height=int(height),
            image_width=int(width),
            hand_keypoints=KEYPOINTS in self.features,
            use_videos=videos or not own,
            environment_state=ENV_STATE in self.features,
        )

    def episode_for(self, seed: int) -> int:
        """The source episode a new episode of ``seed`` is made from (seeds go round)."""
        return self.episodes[seed % len(self.episodes)]


def open_source(root: str | Path) -> Source:
    """The source at ``root``; raises ValueError / FileNotFoundError with what is missing."""
    root = Path(root)
    undo_interrupted_save(root)
    if not dataset_exists(root):
        raise FileNotFoundError(f"no LeRobot dataset in {root} (meta/info.json is missing)")
    info = json.loads((root / "meta" / "info.json").read_text())
    if not (root / EPISODE_LOG).is_file():
        return _recovered_source(root.resolve(), json.dumps(info, sort_keys=True))
    kept = sorted(
        (r for r in read_log(root) if r.get("kept") and isinstance(r.get("seed"), int)),
        key=lambda r: r["episode_index"],
    )
    if not kept:
        raise ValueError(f"{root}: no kept episode with a seed in {EPISODE_LOG}")
    tasks = {(r["task"], r["embodiment"]) for r in kept}
    if len(tasks) != 1:
        raise ValueError(f"{root} mixes tasks/embodiments {sorted(tasks)}: one of each please")
    ((task, embodiment),) = tasks
    return Source(
        root=root,
        task=task,
        embodiment=dataset_embodiment(root, embodiment),
        fps=int(info["fps"]),
        episodes=tuple(int(r["episode_index"]) for r in kept),
        seeds=tuple(int(r["seed"]) for r in kept),
        features=info["features"],
    )


@cache
def _recovered_source(root: Path, info_text: str) -> Source:
    info = json.loads(info_text)
    found = recover(root, info)
    episodes = tuple(sorted(found.seeds))
    return Source(
        root=root,
        task=found.task,
        embodiment=found.embodiment,
        fps=int(info["fps"]),
        episodes=episodes,
        seeds=tuple(found.seeds[e] for e in episodes),
        features=info["features"],
    )


@cache
def _actions(root: Path) -> dict[int, np.ndarray]:
    import pandas as pd  # local: heavy

    frames = pd.concat(
        pd.read_parquet(f, columns=[ACTION, "episode_index", "frame_index"])
        for f in sorted((root / "data").glob("chunk-*/file-*.parquet"))
    ).sort_values(["episode_index", "frame_index"])
    return {
        int(e): np.stack(group[ACTION].to_numpy()).astype(np.float32)
        for e, group in frames.groupby("episode_index")
    }


def load_episode(source: Source, index: int) -> SourceEpisode:
    """Episode ``index`` of ``source`` with its actions."""
    actions = _actions(source.root.resolve()).get(index)
    if actions is None or index not in source.episodes:
        raise ValueError(f"{source.root}: no kept episode {index} (there: {list(source.episodes)})")
    seed = source.seeds[source.episodes.index(index)]
    return SourceEpisode(index, seed, source.task, source.embodiment, actions)
