"""One episode's save as a transaction: on disk whole, or undone.

Saving one episode into a resumed LeRobot v3 dataset adds files (under ``data/``, ``videos/``
and ``meta/episodes/``) and rewrites ``meta/info.json``, ``meta/stats.json`` and, for a new
task, ``meta/tasks.parquet``; we append the episode's line to ``meta/beavr_episodes.jsonl``.
A process killed part-way leaves a data file without its parquet footer and ``info.json``
counting an episode that cannot be read, and LeRobot then refuses the whole dataset.

:func:`episode_save` brackets the save. Before it: copies of the rewritten files, the log's
length and the list of files already there, then the journal (:data:`JOURNAL`), written by
rename. After it: the journal removed, which is the commit. :func:`undo_interrupted_save`,
run before a dataset is opened (:class:`~beavr_sim.datasets.writer.EpisodeWriter`,
:func:`~beavr_sim.datasets.writer.open_dataset`, ``datasets generate``), finds a journal
left by a killed process and puts the dataset back as it was before that save: the files it
added removed, the rewritten ones restored, the log cut back. Undoing is idempotent, so a
kill during the undo is undone by the next open.

The guarantee is against a killed process (SIGKILL, a crash, an interpreter that dies), not
against the machine losing power: files are not fsynced, except the journal.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("beavr_sim.datasets")

#: Present while an episode's save is under way (relative to the dataset root).
JOURNAL = Path("meta") / ".beavr_saving.json"
#: Copies of :data:`REWRITTEN` taken before the save.
BACKUP = Path("meta") / ".beavr_saving"
#: Files the save rewrites in place (restored from the copies on undo).
REWRITTEN = (Path("meta/info.json"), Path("meta/stats.json"), Path("meta/tasks.parquet"))
#: Appended to by the save (cut back to its length on undo).
APPENDED = Path("meta") / "beavr_episodes.jsonl"
#: Folders where the save adds files (anything new there is removed on undo).
ADDED_UNDER = (Path("data"), Path("videos"), Path("meta/episodes"))


@dataclass(frozen=True)
class Undone:
    """What :func:`undo_interrupted_save` did to one dataset."""

    root: Path
    files_removed: tuple[str, ...]
    episodes_left: int

    def describe(self) -> str:
        return (
            f"{self.root}: the last episode's save was cut off (its process was killed); "
            f"undone: {len(self.files_removed)} of its files removed and the metadata put back "
            f"as it was; the {self.episodes_left} episodes saved before it are intact"
        )


def _files_under(root: Path) -> set[str]:
    return {
        path.relative_to(root).as_posix()
        for folder in ADDED_UNDER
        if (root / folder).is_dir()
        for path in (root / folder).rglob("*")
        if path.is_file() or path.is_symlink()
    }


def write_json_atomically(data, fpath: Path) -> None:
    """``data`` as JSON at ``fpath`` (LeRobot's format: indent 4, UTF-8), through a temporary
    file in the same folder renamed over ``fpath``: readers, and a process killed meanwhile,
    see the old file or the new one, never a part."""
    fpath = Path(fpath)
    fpath.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=fpath.parent, prefix=f".{fpath.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=4, ensure_ascii=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, fpath)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _copy_by_rename(source: Path, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.restoring")
    shutil.copy2(source, tmp)
    os.replace(tmp, path)


def begin(root: Path) -> None:
    """Take the copies, then write the journal: from here a kill is undone."""
    root = Path(root)
    undo_interrupted_save(root)  # a journal never nests
    backup = root / BACKUP
    if backup.exists():
        shutil.rmtree(backup)
    backup.mkdir(parents=True)
    rewritten = {}
    for rel in REWRITTEN:
        there = (root / rel).is_file()
        rewritten[rel.as_posix()] = there
        if there:
            shutil.copy2(root / rel, backup / rel.name)
    appended = root / APPENDED
    journal = {
        "rewritten": rewritten,
        "log_bytes": appended.stat().st_size if appended.is_file() else None,
        "files": sorted(_files_under(root)),
    }
    write_json_atomically(journal, root / JOURNAL)


def commit(root: Path) -> None:
    """The save is whole: drop the journal (the commit), then the copies."""
    root = Path(root)
    (root / JOURNAL).unlink()
    shutil.rmtree(root / BACKUP, ignore_errors=True)


def save_pending(root: Path) -> bool:
    """Whether a save at ``root`` began and neither committed nor was undone."""
    return (Path(root) / JOURNAL).is_file()


def undo_interrupted_save(root: str | Path, warn: bool = True) -> Undone | None:
    """Undo the save a killed process left at ``root``; what was done (logged as a warning
    unless not ``warn``), or None when there was nothing to undo."""
    root = Path(root)
    journal_path = root / JOURNAL
    if not journal_path.is_file():
        if (root / BACKUP).exists():  # killed before the journal: nothing was changed
            shutil.rmtree(root / BACKUP, ignore_errors=True)
        return None
    journal = json.loads(journal_path.read_text(encoding="utf-8"))
    before = set(journal["files"])
    removed = sorted(_files_under(root) - before)
    for rel in removed:
        (root / rel).unlink(missing_ok=True)
    for rel, there in journal["rewritten"].items():
        if there:
            _copy_by_rename(root / BACKUP / Path(rel).name, root / rel)
        else:
            (root / rel).unlink(missing_ok=True)
    appended = root / APPENDED
    if journal["log_bytes"] is None:
        appended.unlink(missing_ok=True)
    elif appended.is_file() and appended.stat().st_size > journal["log_bytes"]:
        with appended.open("r+b") as f:
            f.truncate(journal["log_bytes"])
    journal_path.unlink()
    shutil.rmtree(root / BACKUP, ignore_errors=True)
    info = root / "meta" / "info.json"
    episodes = int(json.loads(info.read_text())["total_episodes"]) if info.is_file() else 0
    undone = Undone(root, tuple(removed), episodes)
    if warn:
        log.warning(undone.describe())
    return undone


@contextmanager
def episode_save(root: str | Path) -> Iterator[None]:
    """Around one episode's save: committed when the body returns, undone at once when it
    raises, undone at the next open when the process is killed inside it."""
    root = Path(root)
    begin(root)
    try:
        yield
    except BaseException:
        undo_interrupted_save(root, warn=False)  # the exception says what failed
        raise
    commit(root)
