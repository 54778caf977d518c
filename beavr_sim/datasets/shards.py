"""Shards -> one LeRobot dataset, with LeRobot's own ``aggregate_datasets``.

Parallel generation writes each episode as a shard of its own (a LeRobot dataset of one
episode, or of none when the episode was not kept) with its lines of ``beavr_episodes.jsonl``
and its VR trace. :func:`merge_shards` joins them in the order given (seed order), after the
episodes of an existing dataset at ``out`` if there is one: LeRobot renumbers episodes, frames
and tasks, copies data and videos and aggregates the stats; here the episode log is renumbered
and the traces move into ``<out>/beavr_traces/``.

Files: one data file and one video file per episode and camera (``concatenate_*=False``), as
the serial writer leaves them (it finalizes after every episode), so a merged dataset has the
layout of a serial one and merging is linear in the number of episodes.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beavr_sim.datasets.writer import dataset_exists, require_lerobot

log = logging.getLogger("beavr_sim.datasets")

EPISODE_LOG = Path("meta") / "beavr_episodes.jsonl"
TRACES = "beavr_traces"


@dataclass(frozen=True)
class Shard:
    """One worker's output under ``root``: ``dataset/`` (LeRobot; may hold no episode, or not
    exist when nothing was recorded) with its episode log lines, and ``beavr_traces/``."""

    root: Path

    @property
    def dataset(self) -> Path:
        return self.root / "dataset"

    @property
    def episodes(self) -> int:
        if not dataset_exists(self.dataset):
            return 0
        info = json.loads((self.dataset / "meta" / "info.json").read_text())
        return int(info["total_episodes"])

    @property
    def log_records(self) -> list[dict]:
        path = self.dataset / EPISODE_LOG
        if not path.is_file():
            return []
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    @property
    def traces(self) -> list[Path]:
        return sorted((self.root / TRACES).glob("*.mcap"))


def read_log(root: Path) -> list[dict]:
    path = Path(root) / EPISODE_LOG
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


#: Columns that LeRobot renumbers when merging: their stats in ``meta/stats.json`` are
#: recomputed from the (renumbered) per-episode stats.
BOOKKEEPING = ("episode_index", "index", "task_index")


def _bookkeeping_stats(root: Path) -> None:
    """``aggregate_datasets`` aggregates the sources' ``stats.json`` as they were, so the stats
    of the renumbered columns (episode and frame index) describe the sources' numbering; the
    per-episode stats it writes are renumbered. Recompute those columns' dataset stats from
    them (LeRobot's own ``aggregate_stats``), as a serial run's incremental stats are."""
    import pandas as pd
    from lerobot.datasets.compute_stats import aggregate_stats
    from lerobot.datasets.io_utils import load_stats, write_stats

    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    episodes = pd.concat([pd.read_parquet(f) for f in files]).sort_values("episode_index")
    stats = load_stats(root)
    for key in BOOKKEEPING:
        names = [c.removeprefix(f"stats/{key}/") for c in episodes if c.startswith(f"stats/{key}/")]
        if key not in stats or not names:
            continue
        per_episode = [
            {key: {n: np.asarray(row[f"stats/{key}/{n}"]) for n in names}}
            for _, row in episodes.iterrows()
        ]
        stats[key] = aggregate_stats(per_episode)[key]
    write_stats(stats, root)


def merge_shards(shards: Sequence[Shard], out: Path, repo_id: str) -> int:
    """Merge ``shards`` (in order) into the dataset at ``out``, created if absent, appended to
    if it exists. Returns the number of episodes at ``out`` afterwards.

    ``out`` must not exist or hold a LeRobot dataset; when appending, the merged dataset is
    built beside it and swapped in at the end (an interrupted merge leaves ``out`` as it was).
    """
    require_lerobot()
    from lerobot.datasets.aggregate import aggregate_datasets

    out = Path(out)
    finish_interrupted_swap(out)
    existing = dataset_exists(out)
    if out.exists() and not existing and any(out.iterdir()):
        raise FileExistsError(f"{out} exists and is not a LeRobot dataset")
    sources = [s for s in shards if s.episodes > 0]
    if not sources and not existing:
        raise ValueError(f"nothing to merge into {out}: no shard holds an episode")
    records = read_log(out) if existing else []
    offset = 0
    if existing:
        offset = int(json.loads((out / "meta" / "info.json").read_text())["total_episodes"])
    swap = existing and bool(sources)  # appended episodes: build beside, swap in at the end
    target = _merging(out) if swap else out
    if swap and target.exists():
        shutil.rmtree(target)
    if sources:
        roots = ([out] if existing else []) + [s.dataset for s in sources]
        if out.exists() and not existing:
            out.rmdir()  # an empty folder: LeRobot creates the destination itself
        aggregate_datasets(
            repo_ids=[repo_id] * len(roots),
            aggr_repo_id=repo_id,
            roots=roots,
            aggr_root=target,
            concatenate_videos=False,
            concatenate_data=False,
        )
        _bookkeeping_stats(target)
    # The episode log, renumbered in merge order; the traces beside the data.
    index = offset
    for shard in shards:
        for record in shard.log_records:
            if record.get("kept"):
                record["episode_index"] = index
                index += 1
            records.append(record)
    if index != offset + sum(s.episodes for s in sources):
        raise RuntimeError("the shards' episode logs do not match their episodes")
    (target / EPISODE_LOG).parent.mkdir(parents=True, exist_ok=True)
    (target / EPISODE_LOG).write_text("".join(json.dumps(r) + "\n" for r in records))
    traces = target / TRACES
    if swap and (out / TRACES).is_dir():
        shutil.copytree(out / TRACES, traces, dirs_exist_ok=True)
    for shard in shards:
        for trace in shard.traces:
            traces.mkdir(parents=True, exist_ok=True)
            shutil.copy2(trace, traces / trace.name)
    if swap:  # a kill from here on is finished by finish_interrupted_swap
        backup = _replaced(out)
        out.rename(backup)
        target.rename(out)
        shutil.rmtree(backup)
    return index


def _merging(out: Path) -> Path:
    return out.with_name(out.name + ".merging")


def _replaced(out: Path) -> Path:
    return out.with_name(out.name + ".replaced")


def finish_interrupted_swap(out: Path) -> bool:
    """Finish the swap of an appending merge that a killed process left half done; whether
    there was one. The merged dataset is whole before the old one is moved aside, so with
    ``out`` gone and ``<out>.replaced`` there, ``<out>.merging`` goes into place."""
    out = Path(out)
    backup, merged = _replaced(out), _merging(out)
    if not backup.exists():
        return False
    if not out.exists():
        (merged if merged.exists() else backup).rename(out)
    if backup.exists():  # the old dataset, now replaced (or killed while deleting it)
        shutil.rmtree(backup)
    return True
