"""Task names -> lazy import paths ("module:Class"). The one place tasks are listed."""

from __future__ import annotations

import importlib

from beavr_sim.naming import check_name

TASKS: dict[str, str] = {
    "Playground": "beavr_sim.tasks.playground:Playground",
    "PickupBox": "beavr_sim.tasks.pickup_box:PickupBox",
}


def task_class(name: str):
    """The task class registered as ``name``; raises with the valid names if unknown."""
    module, _, attr = TASKS[check_name("task", name, TASKS)].partition(":")
    return getattr(importlib.import_module(module), attr)
