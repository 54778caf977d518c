"""Task names -> scripted expert classes (lazy "module:Class" paths), the one list of them."""

from __future__ import annotations

import importlib

from beavr_sim.naming import check_name

EXPERTS: dict[str, str] = {
    "PickupBox": "beavr_sim.experts.pick_and_place:PickupBoxExpert",
    "PickPlace": "beavr_sim.experts.pick_and_place:PickPlaceExpert",
    "StackBlocks": "beavr_sim.experts.pick_and_place:StackBlocksExpert",
    "FlipCube": "beavr_sim.experts.flip_cube:FlipCubeExpert",
    "Lantern": "beavr_sim.experts.lantern:LanternExpert",
    "Tape": "beavr_sim.experts.tape:TapeExpert",
    "Pour": "beavr_sim.experts.pour:PourExpert",
}


def expert_class(task: str):
    """The expert class for ``task``; raises with the valid names if there is none."""
    module, _, attr = EXPERTS[check_name("task with a scripted expert", task, EXPERTS)].partition(
        ":"
    )
    return getattr(importlib.import_module(module), attr)
