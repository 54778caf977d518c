"""Which robot made a dataset: ``meta/beavr_robot.json``, written beside LeRobot's ``info.json``
when the embodiment is a robot file.

``info.json``'s ``robot_type`` (and the episode log's ``embodiment``) hold the embodiment's
label (:func:`~beavr_sim.robots.identity.embodiment_label`): a built-in's name, or a robot
file's ``name``. For a robot file this file adds its absolute path and SHA-256, so replay,
augmentation and recovery load the same file again (:func:`dataset_embodiment`), or refuse in
one line when it is gone or changed. Datasets recorded before this file existed named a robot
file by its path; that path is taken as it is.
"""

from __future__ import annotations

import json
from pathlib import Path

from beavr_sim.robots.embodiment import EMBODIMENTS
from beavr_sim.robots.identity import RobotIdentity, locate_robot, robot_identity
from beavr_sim.robots.robot_file import is_robot_file

#: The robot file's identity, relative to the dataset's root.
ROBOT_META = Path("meta") / "beavr_robot.json"


def write_robot_meta(root: str | Path, embodiment: str) -> RobotIdentity:
    """Record ``embodiment``'s identity in the dataset at ``root`` (a robot file's only);
    returns it. A dataset that already records another robot file is refused (one line)."""
    identity = robot_identity(embodiment)
    if not identity.is_file:
        return identity
    meta = Path(root) / ROBOT_META
    if meta.is_file():
        theirs = json.loads(meta.read_text())
        if (theirs.get("path"), theirs.get("sha256")) != (identity.path, identity.sha256):
            raise ValueError(
                f"{root} was recorded with the robot file {theirs.get('path')} "
                f"(sha256 {str(theirs.get('sha256'))[:12]}...), not {identity.path} "
                f"(sha256 {identity.sha256[:12]}...): record into a new folder"
            )
        return identity
    meta.parent.mkdir(parents=True, exist_ok=True)
    meta.write_text(json.dumps(identity.as_dict(), indent=2) + "\n")
    return identity


def dataset_embodiment(root: str | Path, recorded: str) -> str:
    """The embodiment name :func:`~beavr_sim.robots.embodiment.make_embodiment` takes for a
    dataset at ``root`` whose ``robot_type`` / episode log says ``recorded``."""
    if recorded in EMBODIMENTS:
        return recorded
    meta = Path(root) / ROBOT_META
    if meta.is_file():
        identity = json.loads(meta.read_text())
        if identity.get("name") != recorded:
            raise ValueError(
                f"{root}: its embodiment {recorded!r} is not the robot {identity.get('name')!r} "
                f"its {ROBOT_META} records"
            )
        return locate_robot(identity, str(root))
    if is_robot_file(recorded):  # recorded by path
        return recorded
    raise ValueError(
        f"{root}: its embodiment {recorded!r} is not a built-in ({', '.join(EMBODIMENTS)}) and "
        f"no {ROBOT_META} says which robot file it is"
    )
