"""How an embodiment is named outside the process that built it: :class:`RobotIdentity`.

A built-in embodiment is its name. A robot file (``*.toml``, :mod:`beavr_sim.robots.robot_file`)
is its ``name`` (the label datasets, summaries and eval tables show), the file's absolute path
(what :func:`~beavr_sim.robots.embodiment.make_embodiment` loads) and the SHA-256 of its bytes
(which file made a dataset). :func:`locate_robot` finds a recorded robot file again, or says in
one line why it cannot: the file is gone, or it changed since.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from beavr_sim.robots.robot_file import is_robot_file, read_robot_file


@dataclass(frozen=True)
class RobotIdentity:
    """``name``: the label; ``path`` and ``sha256``: the robot file's ("" for a built-in)."""

    name: str
    path: str = ""
    sha256: str = ""

    @property
    def is_file(self) -> bool:
        return bool(self.path)

    def as_dict(self) -> dict[str, str]:
        return {"name": self.name, "path": self.path, "sha256": self.sha256}


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of the file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def robot_identity(embodiment: str) -> RobotIdentity:
    """The identity of ``embodiment``: a built-in's name, or a robot file's path (its ``name``,
    absolute path and hash; raises as :func:`read_robot_file` does when it cannot be read)."""
    if not is_robot_file(embodiment):
        return RobotIdentity(str(embodiment))
    robot = read_robot_file(embodiment)
    return RobotIdentity(robot.name, str(robot.path), file_sha256(robot.path))


def embodiment_label(embodiment: str) -> str:
    """The name to show for ``embodiment``: a built-in's name, a robot file's ``name``."""
    return robot_identity(embodiment).name


def locate_robot(recorded: Mapping[str, object], where: str) -> str:
    """The robot file path a recorded identity (:meth:`RobotIdentity.as_dict`) names, checked
    to exist with the recorded hash; raises ``FileNotFoundError`` / ``ValueError`` in one line
    starting with ``where`` (what recorded it)."""
    name, path, digest = (str(recorded.get(k) or "") for k in ("name", "path", "sha256"))
    if not path:
        raise ValueError(f"{where}: the robot {name!r} is recorded without its file's path")
    if not Path(path).is_file():
        raise FileNotFoundError(
            f"{where} was recorded with the robot file {path} (name {name!r}), which no longer "
            "exists: put it back at that path"
        )
    found = file_sha256(path)
    if digest and found != digest:
        raise ValueError(
            f"{where} was recorded with the robot file {path} (name {name!r}, sha256 "
            f"{digest[:12]}...), which has changed since (sha256 {found[:12]}...): restore it"
        )
    return path
