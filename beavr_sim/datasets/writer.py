"""A LeRobot v3 dataset written episode by episode, each episode safe on disk when it ends.

LeRobot keeps its parquet writers open across episodes and writes their footers only in
``finalize()``: a process killed before that leaves every episode of the session unreadable.
:class:`EpisodeWriter` therefore finalizes after every saved episode and resumes the dataset
for the next one (``LeRobotDataset.resume``); each episode lands in files of its own. Each save
is a transaction (:mod:`beavr_sim.datasets.save_journal`): a process killed inside it leaves a
journal, and the next open puts the dataset back as it was before that episode. A crash
therefore loses only the episode in progress. LeRobot's JSON metadata (``meta/info.json``,
``meta/stats.json``), rewritten in place after every episode, goes through a temporary file
and a rename (:func:`atomic_metadata_writes`), so a reader never sees half a file.

Every dataset the project opens is opened with the PyAV video backend (:data:`VIDEO_BACKEND`,
:func:`open_dataset`): LeRobot's default probes torchcodec first, whose libraries need the
system's FFmpeg of a matching version, and where that is missing it logs the whole load
traceback before falling back to PyAV.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from beavr_sim.datasets.features import check_video_size
from beavr_sim.datasets.quiet import quiet_dataset_writes
from beavr_sim.datasets.robot_meta import write_robot_meta
from beavr_sim.datasets.save_journal import (
    APPENDED,
    episode_save,
    undo_interrupted_save,
    write_json_atomically,
)
from beavr_sim.robots.identity import robot_identity

log = logging.getLogger("beavr_sim.datasets")

#: Video decoding backend for reading back: PyAV works everywhere (torchcodec needs the
#: system's FFmpeg libraries of matching versions).
VIDEO_BACKEND = "pyav"


def require_lerobot():
    """Import LeRobot's dataset class, or explain how to get it."""
    try:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "recording LeRobot datasets needs lerobot >= 0.5 with its dataset extra "
            "(pip install 'lerobot[training]'; Python 3.12). " + str(exc)
        ) from exc
    atomic_metadata_writes()
    return LeRobotDataset


def atomic_metadata_writes() -> None:
    """Route LeRobot's dataset-metadata JSON writes (``write_info``, ``write_stats``: the
    module's ``write_json``) through :func:`write_json_atomically`; once per process."""
    from lerobot.datasets import io_utils

    if io_utils.write_json is not write_json_atomically:
        io_utils.write_json = write_json_atomically


def open_dataset(root: str | Path, repo_id: str | None = None, **kwargs):
    """A recorded dataset, read back with the PyAV video backend (no torchcodec probe);
    ``kwargs`` go to ``LeRobotDataset`` (``episodes``, ``delta_timestamps``, ...). The repo
    id defaults to the one the dataset was written with. A save a killed process left half
    done is undone first (:func:`~beavr_sim.datasets.save_journal.undo_interrupted_save`)."""
    root = Path(root)
    undo_interrupted_save(root)
    if not dataset_exists(root):
        raise FileNotFoundError(f"no LeRobot dataset in {root} (meta/info.json is missing)")
    dataset_cls = require_lerobot()
    kwargs.setdefault("video_backend", VIDEO_BACKEND)
    return dataset_cls(repo_id or f"local/{root.name}", root=root, **kwargs)


def dataset_exists(root: Path) -> bool:
    return (Path(root) / "meta" / "info.json").is_file()


def append_log_line(root: str | Path, record: Mapping) -> None:
    """One episode's line in ``meta/beavr_episodes.jsonl``."""
    path = Path(root) / APPENDED
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        f.write(json.dumps(dict(record)) + "\n")


class EpisodeWriter:
    """Frames in, one durable LeRobot episode per :meth:`save_episode`.

    ``robot_type``: the embodiment (a built-in's name or a robot file's path); ``info.json``
    records its label and, for a robot file, ``meta/beavr_robot.json`` its path and hash
    (:mod:`beavr_sim.datasets.robot_meta`).
    """

    def __init__(
        self,
        root: str | Path,
        repo_id: str,
        features: dict[str, dict],
        fps: int,
        robot_type: str,
        use_videos: bool = True,
        overwrite: bool = False,
    ):
        quiet_dataset_writes()  # before LeRobot loads ``datasets``: no encoder banners, bars
        if use_videos:
            for ft in features.values():
                if ft.get("dtype") == "video":
                    check_video_size(int(ft["shape"][0]), int(ft["shape"][1]))
        self.root = Path(root)
        self.repo_id = repo_id
        self.fps = int(fps)
        self._dataset_cls = require_lerobot()
        identity = robot_identity(robot_type)
        undo_interrupted_save(self.root)
        if dataset_exists(self.root):
            if overwrite:
                shutil.rmtree(self.root)
            else:
                self._check_compatible(features, fps)
        elif self.root.exists() and any(self.root.iterdir()):
            if not overwrite:
                raise FileExistsError(
                    f"{self.root} exists and is not a LeRobot dataset; pick a new folder or "
                    "pass overwrite"
                )
            shutil.rmtree(self.root)
        if not dataset_exists(self.root):
            self._dataset = self._dataset_cls.create(
                repo_id,
                fps,
                features,
                root=self.root,
                robot_type=identity.name,
                use_videos=use_videos,
                video_backend=VIDEO_BACKEND,
                metadata_buffer_size=1,
            )
        else:
            self._dataset = None  # resumed when the first frame arrives
        write_robot_meta(self.root, robot_type)  # a robot file's path and hash
        self.features = features
        self.frames_in_episode = 0
        self.episodes_saved = 0

    def _check_compatible(self, features: Mapping[str, dict], fps: int) -> None:
        info = json.loads((self.root / "meta" / "info.json").read_text())
        theirs = {k: (v["dtype"], tuple(v["shape"])) for k, v in info["features"].items()}
        for key, ft in features.items():
            if theirs.get(key) != (ft["dtype"], tuple(ft["shape"])):
                raise ValueError(
                    f"{self.root} holds a dataset whose feature {key!r} is {theirs.get(key)}, "
                    f"not {(ft['dtype'], tuple(ft['shape']))}: record into a new folder"
                )
        if int(info["fps"]) != int(fps):
            raise ValueError(f"{self.root} was recorded at {info['fps']} fps, not {fps}")

    @property
    def num_episodes(self) -> int:
        """Episodes on disk."""
        if not dataset_exists(self.root):
            return 0
        return int(json.loads((self.root / "meta" / "info.json").read_text())["total_episodes"])

    def _open(self):
        if self._dataset is None:
            self._dataset = self._dataset_cls.resume(
                self.repo_id, root=self.root, video_backend=VIDEO_BACKEND
            )
        return self._dataset

    def add_frame(self, frame: dict[str, np.ndarray], task: str) -> None:
        self._open().add_frame({**frame, "task": task})
        self.frames_in_episode += 1

    def save_episode(self, log_record: dict | None = None) -> bool:
        """Write the episode's frames; on disk and loadable when this returns, or (killed
        inside) undone at the next open. ``log_record``, given its ``episode_index``, is the
        episode's line in ``meta/beavr_episodes.jsonl``, written in the same transaction.
        False if the episode was empty (nothing written)."""
        if self.frames_in_episode == 0:
            return False
        dataset = self._open()
        try:
            with episode_save(self.root):
                dataset.save_episode()
                dataset.finalize()  # parquet footers and metadata
                if log_record is not None:
                    log_record = {**log_record, "episode_index": self.num_episodes - 1}
                    append_log_line(self.root, log_record)
        finally:  # saved, or undone on disk: the next episode resumes from there
            self._dataset = None
            self.frames_in_episode = 0
        self.episodes_saved += 1
        return True

    def discard_episode(self) -> None:
        """Drop the frames of the episode in progress."""
        if self._dataset is not None and self.frames_in_episode:
            self._dataset.clear_episode_buffer()
        self.frames_in_episode = 0

    def close(self) -> None:
        """Drop an unfinished episode and close the files (the saved episodes stay)."""
        self.discard_episode()
        if self._dataset is not None:
            self._dataset.finalize()
            self._dataset = None
