"""Scripted experts that pick objects and put them down: PickupBox, PickPlace, StackBlocks.

Each pick is a front pinch (see :mod:`beavr_sim.experts.grasps`) by the hand whose arm base is
nearest the object, at a heading around the arm's pinch heading; the object is carried at a
safe height and set down so that its centre ends where the task wants it. When that hand
cannot reach the goal and another can (arms on close shoulders, each reaching little past the
midline), the first sets the object down on the way, where both reach, and the other takes it
from there.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert


class PickAndPlaceExpert(ScriptedExpert):
    """Base of the experts here: :meth:`transfer` one object to a goal position."""

    def heading_for(self, obj: str, symmetry: float | None, effector: str) -> float:
        """Hand heading for ``effector`` pinching ``obj``: across a pair of its faces when it
        has a rotational ``symmetry`` (rad) about the vertical, the one nearest the arm's
        pinch heading; the pinch heading itself when the object is round."""
        reference = self.pinch_heading(effector)
        if symmetry is None:
            return reference
        R = self.task.objects[obj].R_world_body(self.env.data)
        return grasps.fold_heading(float(np.arctan2(R[1, 0], R[0, 0])), symmetry, reference)

    def nearest_effector(self, xy) -> str:
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        return min(bases, key=lambda n: float(np.linalg.norm(bases[n] - np.asarray(xy[:2]))))

    def reaches_to_place(self, effector: str, centre, heading: float) -> bool:
        """Whether ``effector`` can set an object down with its centre at ``centre``, holding
        it in a front pinch at ``heading`` (over it, and down at it)."""
        R = grasps.R_world_palm_down(heading)
        return self.reaches(
            effector,
            [grasps.T_world_hand_pinching(np.add(centre, [0, 0, h]), R) for h in (0.12, 0.0)],
        )

    def transfer(
        self, obj: str, goal_centre, symmetry: float | None, effector: str | None = None
    ) -> Iterator[Move]:
        """Pick ``obj`` and put it down with its centre at ``goal_centre`` (world), with
        ``effector`` or else the hand nearest the object; relayed through another hand when
        the first cannot reach the goal (:meth:`relay_point`)."""
        start = self.task.objects[obj].pos(self.env.data)
        goal = np.asarray(goal_centre, float)
        if effector is None:
            effector = self.nearest_effector(start)
        heading = self.heading_for(obj, symmetry, effector)
        if not self.reaches_to_place(effector, goal, heading):
            others = [
                n
                for n in self.effector_names
                if n != effector and self.reaches_to_place(n, goal, self.pinch_heading(n))
            ]
            if others:
                relay = self.relay_point(start, goal, effector, others[0])
                yield from self.pick(effector, obj, heading)
                yield from self.place(effector, relay, held=obj)
                yield from self.retreat(effector)
                effector = others[0]
                heading = self.heading_for(obj, symmetry, effector)
        yield from self.pick(effector, obj, heading)
        yield from self.place(effector, goal, held=obj)
        yield from self.retreat(effector)

    def relay_point(self, start, goal, giver: str, taker: str) -> np.ndarray:
        """Where ``giver`` sets the object down for ``taker``: on the way from ``start`` to
        ``goal``, where it crosses the line midway between the two arms' bases (at the
        object's resting height)."""
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        a, b = bases[giver], bases[taker]
        normal = (b - a) / np.linalg.norm(b - a)
        mid = (a + b) / 2
        d_start = float(np.dot(start[:2] - mid, normal))
        d_goal = float(np.dot(goal[:2] - mid, normal))
        s = d_start / (d_start - d_goal) if d_start * d_goal < 0 else 0.5
        return np.array([*(start[:2] + s * (goal[:2] - start[:2])), start[2]])


class PickupBoxExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        box = self.task.objects["box"].pos(self.env.data)
        target = self.task.fixtures["target"].pos(self.env.data)
        yield from self.transfer("box", (target[0], target[1], box[2]), symmetry=np.pi / 2)


class PickPlaceExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        item = self.task.objects["item"].pos(self.env.data)
        target = self.task.fixtures["target"].pos(self.env.data)
        yield from self.transfer("item", (target[0], target[1], item[2]), None)


class StackBlocksExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        from beavr_sim.tasks.stack_blocks import LARGE_HALF, SMALL_HALF

        data = self.env.data
        target = self.task.fixtures["target"].pos(data)
        large = self.task.objects["large_block"].pos(data)
        yield from self.transfer("large_block", (target[0], target[1], large[2]), np.pi / 2)
        large = self.task.objects["large_block"].pos(data)
        on_top = large + [0.0, 0.0, LARGE_HALF + SMALL_HALF]
        yield from self.transfer("small_block", on_top, np.pi / 2)
