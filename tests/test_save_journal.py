"""A process killed inside an episode's save: the next open undoes that save, the episodes
before it load, and recording goes on (beavr_sim.datasets.save_journal).

Each case runs a child that saves two episodes, then is SIGKILLed by itself at one chosen
point inside the third save, so where the kill lands is decided, not timed."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("lerobot")

from beavr_sim.datasets.save_journal import BACKUP, JOURNAL, save_pending
from beavr_sim.datasets.writer import EpisodeWriter, open_dataset

FRAMES = 6
REPO_ID = "local/journal"

#: Where the child kills itself during its third save, and the kill's hook (code run in the
#: child after the first two episodes are saved). ``die()`` is SIGKILL to itself.
KILL_POINTS = {
    # LeRobot has written the episode's frames; the data file has no footer yet.
    "data_without_footer": """
        import pyarrow.parquet as pq
        original = pq.ParquetWriter.write_table
        def write_table(self, table, *a, **k):
            original(self, table, *a, **k)
            if "/data/" in str(self.where):
                die()
        pq.ParquetWriter.write_table = write_table
    """,
    # meta/info.json already counts the episode.
    "info_counts_it": """
        from lerobot.datasets import io_utils
        original = io_utils.write_json
        def write_json(data, path):
            original(data, path)
            if str(path).endswith("info.json"):
                die()
        io_utils.write_json = write_json
    """,
    # Everything written, the log line too; the journal not yet removed.
    "before_commit": """
        from beavr_sim.datasets import save_journal
        save_journal.commit = lambda root: die()
    """,
}

CHILD = """
import os, signal, sys
import numpy as np
from beavr_sim.datasets.writer import EpisodeWriter

def die():
    os.kill(os.getpid(), signal.SIGKILL)

root, videos, hook = sys.argv[1], sys.argv[2] == "1", sys.argv[3]
features = {"action": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}}
if videos:
    features["observation.images.top"] = {
        "dtype": "video", "shape": (64, 64, 3), "names": ["height", "width", "channels"]
    }

def episode(writer, k):
    for i in range(FRAMES):
        frame = {"action": np.full(2, 10 * k + i, np.float32)}
        if videos:
            frame["observation.images.top"] = np.full((64, 64, 3), 40 * k, np.uint8)
        writer.add_frame(frame, task="PickupBox")
    assert writer.save_episode({"kept": True, "seed": k})

writer = EpisodeWriter(root, REPO_ID, features, 10, "xarm7_leap_right", use_videos=videos)
episode(writer, 0)
episode(writer, 1)
exec(hook)
episode(writer, 2)
print("not killed")
""".replace("FRAMES", str(FRAMES)).replace("REPO_ID", repr(REPO_ID))


def _features(videos: bool) -> dict:
    features = {"action": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}}
    if videos:
        features["observation.images.top"] = {
            "dtype": "video",
            "shape": (64, 64, 3),
            "names": ["height", "width", "channels"],
        }
    return features


def _log(root: Path) -> list[dict]:
    return [
        json.loads(x) for x in (root / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    ]


def _killed_inside_the_third_save(root: Path, point: str, videos: bool) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(root), "1" if videos else "0",
         textwrap.dedent(KILL_POINTS[point])],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, proc.stdout + proc.stderr
    assert save_pending(root)  # the kill landed inside the save


@pytest.mark.parametrize(
    ("point", "videos"),
    [(p, False) for p in KILL_POINTS] + [("before_commit", True)],
)
def test_a_save_killed_midway_is_undone_and_recording_goes_on(tmp_path, point, videos, caplog):
    root = tmp_path / "ds"
    _killed_inside_the_third_save(root, point, videos)

    ds = open_dataset(root)  # undoes the third save first
    assert "save was cut off" in caplog.text
    assert not save_pending(root) and not (root / BACKUP).exists()
    assert ds.num_episodes == 2 and len(ds) == 2 * FRAMES
    assert float(ds[len(ds) - 1]["action"][0]) == 10 + FRAMES - 1  # episode 1's last frame
    if videos:
        assert ds[0]["observation.images.top"].shape == (3, 64, 64)
    assert [(r["episode_index"], r["seed"]) for r in _log(root)] == [(0, 0), (1, 1)]

    writer = EpisodeWriter(root, REPO_ID, _features(videos), 10, "xarm7_leap_right", videos)
    for i in range(FRAMES):
        frame = {"action": np.full(2, 20 + i, np.float32)}
        if videos:
            frame["observation.images.top"] = np.full((64, 64, 3), 80, np.uint8)
        writer.add_frame(frame, task="PickupBox")
    assert writer.save_episode({"kept": True, "seed": 2})
    ds = open_dataset(root)
    assert ds.num_episodes == 3 and len(ds) == 3 * FRAMES
    assert float(ds[len(ds) - 1]["action"][0]) == 20 + FRAMES - 1
    assert [r["episode_index"] for r in _log(root)] == [0, 1, 2]


def test_a_save_that_raises_leaves_the_dataset_as_it_was(tmp_path, monkeypatch):
    """An exception inside the save (a full disk, an encoder error) undoes it at once; the
    writer resumes from disk for the next episode."""
    root = tmp_path / "ds"
    writer = EpisodeWriter(root, REPO_ID, _features(False), 10, "xarm7_leap_right", False)

    def episode(value: float) -> None:
        for _ in range(FRAMES):
            writer.add_frame({"action": np.full(2, value, np.float32)}, task="PickupBox")

    episode(0.0)
    assert writer.save_episode({"kept": True, "seed": 0})
    from lerobot.datasets import io_utils

    original = io_utils.write_json

    def disk_full(data, path):
        if str(path).endswith("stats.json"):
            raise OSError(28, "No space left on device")
        original(data, path)

    monkeypatch.setattr(io_utils, "write_json", disk_full)
    episode(1.0)
    with pytest.raises(OSError, match="No space left"):
        writer.save_episode({"kept": True, "seed": 1})
    assert not save_pending(root)
    assert open_dataset(root).num_episodes == 1
    assert [r["seed"] for r in _log(root)] == [0]

    monkeypatch.setattr(io_utils, "write_json", original)
    episode(2.0)
    assert writer.save_episode({"kept": True, "seed": 2})
    ds = open_dataset(root)
    assert ds.num_episodes == 2 and float(ds[len(ds) - 1]["action"][0]) == 2.0
    assert [(r["episode_index"], r["seed"]) for r in _log(root)] == [(0, 0), (1, 2)]


def test_copies_left_without_a_journal_are_dropped_and_nothing_else_changes(tmp_path):
    """Killed while taking the copies, before the journal: the dataset was not touched yet."""
    root = tmp_path / "ds"
    writer = EpisodeWriter(root, REPO_ID, _features(False), 10, "xarm7_leap_right", False)
    writer.add_frame({"action": np.zeros(2, np.float32)}, task="PickupBox")
    assert writer.save_episode()
    info = (root / "meta" / "info.json").read_bytes()
    (root / BACKUP).mkdir()
    (root / BACKUP / "info.json").write_text("{}")
    assert open_dataset(root).num_episodes == 1
    assert not (root / BACKUP).exists() and not (root / JOURNAL).exists()
    assert (root / "meta" / "info.json").read_bytes() == info
