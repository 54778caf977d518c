"""Scripted experts that pick objects and put them down: PickupBox, PickPlace, StackBlocks.

Each pick is a front pinch (see :mod:`beavr_sim.experts.grasps`) by the hand whose arm base is
nearest the middle of the way from the object to where it goes; the object is carried at a
safe height and set down so that its centre ends where the task wants it.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert


class PickAndPlaceExpert(ScriptedExpert):
    """Base of the experts here: :meth:`transfer` one object to a goal position."""

    def heading_for(self, obj: str, symmetry: float | None) -> float:
        """Hand heading for pinching ``obj``: across a pair of its faces when it has a
        rotational ``symmetry`` (rad) about the vertical, straight ahead when it is round."""
        if symmetry is None:
            return 0.0
        R = self.task.objects[obj].R_world_body(self.env.data)
        return grasps.fold_heading(float(np.arctan2(R[1, 0], R[0, 0])), symmetry)

    def nearest_effector(self, xy) -> str:
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        return min(bases, key=lambda n: float(np.linalg.norm(bases[n] - np.asarray(xy[:2]))))

    def transfer(
        self, obj: str, goal_centre, symmetry: float | None, effector: str | None = None
    ) -> Iterator[Move]:
        """Pick ``obj`` and put it down with its centre at ``goal_centre`` (world), with
        ``effector`` or else the hand nearest the middle of the way."""
        start = self.task.objects[obj].pos(self.env.data)
        if effector is None:
            effector = self.nearest_effector((start[:2] + np.asarray(goal_centre)[:2]) / 2)
        yield from self.pick(effector, obj, self.heading_for(obj, symmetry))
        yield from self.place(effector, goal_centre, held=obj)
        yield from self.retreat(effector)


class PickupBoxExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        box = self.task.objects["box"].pos(self.env.data)
        target = self.task.fixtures["target"].pos(self.env.data)
        yield from self.transfer("box", (target[0], target[1], box[2]), symmetry=np.pi / 2)


class PickPlaceExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        item = self.task.objects["item"].pos(self.env.data)
        target = self.task.fixtures["target"].pos(self.env.data)
        yield from self.transfer(
            "item", (target[0], target[1], item[2]), None, effector=self.nearest_effector(item)
        )


class StackBlocksExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        from beavr_sim.tasks.stack_blocks import LARGE_HALF, SMALL_HALF

        data = self.env.data
        target = self.task.fixtures["target"].pos(data)
        large_z = self.task.objects["large_block"].pos(data)[2]
        large = self.task.objects["large_block"].pos(data)
        yield from self.transfer(
            "large_block",
            (target[0], target[1], large_z),
            np.pi / 2,
            effector=self.nearest_effector(large),
        )
        large = self.task.objects["large_block"].pos(data)
        small = self.task.objects["small_block"].pos(data)
        on_top = large + [0.0, 0.0, LARGE_HALF + SMALL_HALF]
        yield from self.transfer(
            "small_block", on_top, np.pi / 2, effector=self.nearest_effector(small)
        )
