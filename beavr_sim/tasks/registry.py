"""Task names -> lazy import paths ("module:Class"). The one place tasks are listed."""

from __future__ import annotations

import importlib

from beavr_sim.naming import check_name

TASKS: dict[str, str] = {
    "Playground": "beavr_sim.tasks.playground:Playground",
    "PickupBox": "beavr_sim.tasks.pickup_box:PickupBox",
    "PickPlace": "beavr_sim.tasks.pick_place:PickPlace",
    "StackBlocks": "beavr_sim.tasks.stack_blocks:StackBlocks",
    "FlipCube": "beavr_sim.tasks.flip_cube:FlipCube",
    "Lantern": "beavr_sim.tasks.lantern:Lantern",
    "Tape": "beavr_sim.tasks.tape:Tape",
    "Pour": "beavr_sim.tasks.pour:Pour",
}


def task_class(name: str):
    """The task class registered as ``name``; raises with the valid names if unknown."""
    module, _, attr = TASKS[check_name("task", name, TASKS)].partition(":")
    return getattr(importlib.import_module(module), attr)


def _squash(name: str) -> str:
    return name.lower().replace("_", "").replace("-", "").replace(" ", "")


def canonical_task_name(name: str) -> str:
    """The registered spelling of a task name given in any case, with or without ``_``/``-``
    (``pour`` -> ``Pour``, ``pick_place`` -> ``PickPlace``); raises with the valid names."""
    by_squashed = {_squash(t): t for t in TASKS}
    if isinstance(name, str) and _squash(name) in by_squashed:
        return by_squashed[_squash(name)]
    return check_name("task", name, TASKS)
