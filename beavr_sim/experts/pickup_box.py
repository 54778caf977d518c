"""Scripted expert for PickupBox and PickPlace: pinch the item, carry it over the target
area's centre, set it down, let go."""

from __future__ import annotations

from collections.abc import Iterator

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert


class PickAndPlaceExpert(ScriptedExpert):
    """Pick ``item`` and place it, centred, on the target area."""

    item = "box"
    #: Rotational symmetry of the item about its vertical axis (rad): a square box 90 deg.
    symmetry = grasps.np.pi / 2

    def script(self) -> Iterator[Move]:
        effector = self.effector_names[0]
        data = self.env.data
        item = self.task.objects[self.item]
        R = item.R_world_body(data)
        heading = grasps.fold_heading(float(grasps.np.arctan2(R[1, 0], R[0, 0])), self.symmetry)
        rest_z = item.pos(data)[2]
        yield from self.pick(effector, self.item, heading)
        target = self.task.fixtures["target"].pos(data)
        yield from self.place(effector, (target[0], target[1], rest_z))
