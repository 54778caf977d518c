"""One augmented episode, recorded: the per-seed work of ``datasets augment``.

:func:`augment_episode` is what ``datasets generate``'s per-seed work calls when the run has
a source: the new seed's source episode (:meth:`Source.episode_for`; with two arms the one
whose objects stood nearest the new scene's, :func:`nearest_episode`, among the source
episodes and, for two mirror-image arms, their mirror images, :mod:`.mirror`) is
replayed and segmented (once per process), the new scene is run (:mod:`.execute`) while the
recorder writes its frames, and the episode is kept if the task's checker said success. The
episode's line in ``meta/beavr_episodes.jsonl`` names the new seed, the source dataset, episode
and seed, whether it was mirrored, the segments and, for a failure, its reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from beavr_sim.datasets.augment.execute import ExecuteConfig, Rig, execute
from beavr_sim.datasets.augment.mirror import Mirror, reflect
from beavr_sim.datasets.augment.replay import Trajectory, replay
from beavr_sim.datasets.augment.segments import Segment, SegmentationError, find_segments
from beavr_sim.datasets.augment.source import Source, load_episode, open_source
from beavr_sim.datasets.features import RecordingConfig
from beavr_sim.datasets.recorder import EpisodeRecorder


@dataclass(frozen=True)
class Augmented:
    """What became of one seed: the checker's verdict, whether it was written, and why not."""

    success: bool
    written: bool
    frames: int
    reason: str = ""


@cache
def _rig(task: str, embodiment: str) -> Rig:
    return Rig(task, embodiment)


@cache
def _mirror(task: str, embodiment: str) -> Mirror | None:
    rig = _rig(task, embodiment)
    return Mirror.of(rig.env)  # leaves the rig's joints at home: reset it before use


@cache
def _plan(root: str, index: int, mirrored: bool = False) -> tuple[Trajectory, list[Segment]]:
    source = open_source(root)
    traj = replay(load_episode(source, index))
    if mirrored:
        mirror = _mirror(source.task, source.embodiment)
        if mirror is None:
            raise ValueError(f"{source.embodiment}'s arms are not mirror images: no mirrored plan")
        traj = mirror.trajectory(traj)
    return traj, find_segments(traj)


def nearest_episode(source: Source, rig: Rig, mirrored: bool = False) -> tuple[int, bool]:
    """The source episode whose free objects stood nearest (summed distance in the table
    plane) to where they stand in ``rig``'s new scene (MimicGen's nearest-object selection):
    with two arms, the one that handled them there reaches them. With ``mirrored``, the
    episodes' mirror images are candidates too; returns (episode, whether mirrored)."""
    root = str(source.root.resolve())
    here = {o: rig.things.pose(rig.env, o)[0][:2] for o in rig.things.objects}

    def distance(candidate: tuple[int, bool]) -> float:
        start = _start(root, candidate[0])
        if candidate[1]:
            start = reflect(start)
        return sum(float(np.linalg.norm(start[o][:2] - p)) for o, p in here.items())

    flips = (False, True) if mirrored else (False,)
    return min(((e, f) for f in flips for e in source.episodes), key=distance)


@cache
def _start(root: str, index: int) -> dict[str, np.ndarray]:
    """The free objects' positions at the reset of source episode ``index``."""
    source = open_source(root)
    seed = source.seeds[source.episodes.index(index)]
    rig = _rig(source.task, source.embodiment)
    rig.env.reset(seed=seed)
    return {o: rig.things.pose(rig.env, o)[0].copy() for o in rig.things.objects}


def augment_episode(
    source_root: str,
    task: str,
    seed: int,
    embodiment: str,
    config: RecordingConfig,
    keep_failed: bool,
    writer,
    make_writer=None,
) -> Augmented:
    """One new episode at ``seed`` from the source at ``source_root`` into ``writer`` (or
    ``make_writer()``)."""
    source = open_source(source_root)
    if (source.task, source.embodiment) != (task, embodiment):
        raise ValueError(
            f"{source_root} holds {source.task} on {source.embodiment}, not {task} on {embodiment}"
        )
    rig = _rig(task, embodiment)
    mirror = _mirror(task, embodiment) if len(rig.arms) > 1 else None
    rig.reset(seed)
    index, mirrored = source.episode_for(seed), False
    if len(rig.arms) > 1:  # the source episode whose objects stood nearest: the arm that reaches
        index, mirrored = nearest_episode(source, rig, mirror is not None)
        rig.reset(seed)  # the sources' resets were looked at on the same env
    try:
        traj, segments = _plan(str(Path(source_root).resolve()), index, mirrored)
    except SegmentationError as exc:
        return Augmented(False, False, 0, f"segmenting: {exc}")
    if writer is None:
        writer = make_writer()
    recorder = EpisodeRecorder(writer, rig.env, config)
    recorder.begin()
    try:
        result = execute(
            rig, traj, segments, seed, ExecuteConfig(tail_seconds=config.tail_seconds), recorder
        )
        written = recorder.end(
            keep=result.success or keep_failed,
            success=result.success,
            seed=seed,
            source=f"augment {Path(source_root).name} episode {index}",
            source_episode=index,
            source_seed=traj.episode.seed,
            source_mirrored=mirrored,
            segments=[f"{s.kind}:{s.object}@{s.reference}" for s in segments],
            failure=result.reason or None,
            checker=result.details,
            carried=result.transforms,
            guard_blocks=result.guard_blocks,
        )
    finally:
        recorder.close()
    frames = recorder.frames if written else 0
    return Augmented(result.success, bool(written), frames, result.reason)
