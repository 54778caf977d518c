"""Validation shared by the plugin configs (no LeRobot import): tasks, embodiments, cameras,
sizes. Every error names the valid choices (:class:`beavr_sim.naming.UnknownNameError`)."""

from __future__ import annotations

import math
from collections.abc import Iterable

from beavr_sim.envs.scene import camera_names
from beavr_sim.naming import check_name
from beavr_sim.robots import Embodiment, make_embodiment
from beavr_sim.robots.embodiment import embodiment_layout
from beavr_sim.robots.robot_file import is_robot_file
from beavr_sim.tasks.registry import canonical_task_name, task_class

#: The embodiment every plugin config defaults to.
DEFAULT_EMBODIMENT = "xarm7_leap_right"


def check_task(task: object, embodiment: str | None = None) -> str:
    """The registered spelling of ``task`` (any case, ``pick_place`` or ``PickPlace``); raises
    listing the tasks, or the embodiments the task supports when ``embodiment`` is not one."""
    if not isinstance(task, str):
        check_name("task", task, ())  # raises with the valid names
    name = canonical_task_name(task)
    if embodiment is not None:
        supported = task_class(name).embodiments
        if supported is not None:  # a robot file runs the tasks of its layout
            layout = embodiment_layout(embodiment) if is_robot_file(embodiment) else embodiment
            check_name("embodiment", layout or embodiment, supported, f"for task {name}")
    return name


def check_embodiment(name: object) -> Embodiment:
    """The embodiment called ``name``; raises listing the valid names."""
    return make_embodiment(name)  # type: ignore[arg-type]


def check_cameras(
    cameras: Iterable[str], embodiment: Embodiment, placed: Iterable[str] = ()
) -> tuple[str, ...]:
    """``cameras`` as a tuple, each one of the embodiment's scene cameras or ``placed`` (twin
    cameras a ``camera_poses`` file adds to the scene), none repeated."""
    if isinstance(cameras, str):
        cameras = [c for c in cameras.split(",") if c.strip()]
    valid = tuple(dict.fromkeys(camera_names(embodiment) + tuple(placed)))
    out = tuple(
        check_name("camera", c.strip(), valid, f"for embodiment {embodiment.name}") for c in cameras
    )
    if len(set(out)) != len(out):
        raise ValueError(f"cameras repeat: {list(out)}")
    return out


def check_positive_int(kind: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{kind} must be a positive integer, got {value!r}")
    return value


def check_image_size(height: object, width: object) -> None:
    check_positive_int("image_height", height)
    check_positive_int("image_width", width)


def episode_steps(task: str, fps: int, episode_length: int | None) -> int:
    """Control steps of an episode: ``episode_length``, or the task's time limit at ``fps``."""
    if episode_length is not None:
        return check_positive_int("episode_length", episode_length)
    return math.ceil(task_class(task).max_episode_seconds * fps - 1e-9)
