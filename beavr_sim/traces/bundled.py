"""The bundled VR trace of a task on an embodiment, names checked before files.

:func:`find_bundled_trace` is what a command line calls for ``--source trace`` without
``--trace``: a misspelled task or embodiment gets the "Unknown ... Did you mean" error of
:mod:`beavr_sim.naming`, a task that does not run on the embodiment says where it runs, and
only then is the file looked up (:func:`beavr_sim.assets.bundled_trace`: a missing one names
the bundled traces and the ``python -m beavr_sim.traces synth`` command that makes it).
"""

from __future__ import annotations

from pathlib import Path

from beavr_sim.assets import DEFAULT_TRACE_EMBODIMENT, bundled_trace
from beavr_sim.naming import check_name
from beavr_sim.robots import EMBODIMENTS
from beavr_sim.robots.embodiment import embodiment_layout
from beavr_sim.robots.robot_file import is_robot_file
from beavr_sim.tasks.registry import canonical_task_name, task_class


class TaskEmbodimentError(ValueError):
    """A known task on a known embodiment it does not run on."""


def check_task_embodiment(task: str, embodiment: str | None = None) -> tuple[str, str]:
    """(registered task name, embodiment), or raise naming the cause: an unknown task or
    embodiment (with the valid names), or a task that does not run on the embodiment."""
    name = canonical_task_name(task)
    embodiment = DEFAULT_TRACE_EMBODIMENT if embodiment is None else embodiment
    if is_robot_file(embodiment):  # a robot file runs the tasks and traces of its layout
        embodiment = embodiment_layout(embodiment) or embodiment
    check_name("embodiment", embodiment, EMBODIMENTS)
    supported = task_class(name).embodiments
    if supported is not None and embodiment not in supported:
        raise TaskEmbodimentError(
            f"{name} does not run on {embodiment} (runs on {', '.join(supported)})"
        )
    return name, embodiment


def find_bundled_trace(task: str, embodiment: str | None = None) -> Path:
    """The bundled trace of ``task`` on ``embodiment`` (default: the one-armed rig), checked to
    exist; names are checked first (see the module docstring)."""
    name, embodiment = check_task_embodiment(task, embodiment)
    return bundled_trace(name, embodiment)
