"""Scripted experts that pick objects and put them down: PickupBox, PickPlace, StackBlocks.

Each pick is a front pinch (see :mod:`beavr_sim.experts.grasps`) at a heading around the arm's
pinch heading; the object is carried at a safe height and set down so that its centre ends
where the task wants it. The hand that does it is the one nearest the object that reaches the
object, the way and the goal (IK trials; a goal inside a target area may move towards the
hand). When none does (arms on close shoulders, each reaching little past the middle), the
nearest sets the object down where another reaches it, and that one takes it on.
"""

from __future__ import annotations

from collections.abc import Iterator

import mink
import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert
from beavr_sim.tasks.pick_place import AREA_HALF as ITEM_AREA_HALF
from beavr_sim.tasks.pickup_box import AREA_HALF as BOX_AREA_HALF
from beavr_sim.tasks.stack_blocks import AREA_HALF as STACK_AREA_HALF
from beavr_sim.tasks.stack_blocks import LARGE_HALF, SMALL_HALF

#: The carry to the goal is tried at this many steps.
CARRY_CHECKS = 3
#: Goal points tried per hand, from the goal itself to ``slack`` nearer the hand.
GOAL_STEPS = 3
#: An object set down off a target area's centre stays this far inside its edges (m).
AREA_MARGIN = 0.03
#: A relayed object is set down this far (m) from the others' footprints, at one of these
#: offsets (m) along and across the line midway between the arms, the nearest first.
RELAY_GAP = 0.02
RELAY_OFFSETS = np.arange(-0.15, 0.151, 0.03)


def area_slack(area_half) -> float:
    """How far off the centre of a target area of half-sizes ``area_half`` an object's centre
    may be set down (whatever the area's yaw)."""
    return max(0.0, float(min(area_half)) - AREA_MARGIN)


class PickAndPlaceExpert(ScriptedExpert):
    """Base of the experts here: :meth:`transfer` one object to a goal position."""

    def heading_for(self, obj: str, symmetry: float | None, effector: str) -> float:
        """Hand heading for ``effector`` pinching ``obj``: across a pair of its faces when it
        has a rotational ``symmetry`` (rad) about the vertical, the one nearest the arm's
        pinch heading that the hand reaches the object with (the next pair round if not);
        the pinch heading itself when the object is round."""
        reference = self.pinch_heading(effector)
        if symmetry is None:
            return reference
        R = self.task.objects[obj].R_world_body(self.env.data)
        nearest = grasps.fold_heading(float(np.arctan2(R[1, 0], R[0, 0])), symmetry, reference)
        others = sorted((nearest + symmetry, nearest - symmetry), key=lambda h: abs(h - reference))
        for heading in (nearest, *others):
            if self.reaches(effector, self.pick_poses(obj, heading)):
                return heading
        return nearest

    def reaches_to_place(self, effector: str, centre, heading: float) -> bool:
        """Whether ``effector`` can set an object down with its centre at ``centre``, holding
        it in a front pinch at ``heading`` (over it, and down at it)."""
        R = grasps.R_world_palm_down(heading)
        return self.reaches(
            effector,
            [grasps.T_world_hand_pinching(np.add(centre, [0, 0, h]), R) for h in (0.12, 0.0)],
        )

    def reaches_to_carry(self, effector: str, obj: str, heading: float, goal) -> bool:
        """Whether ``effector`` can pick ``obj`` at ``heading``, carry it over the way to
        ``goal`` (CARRY_CHECKS points on it) and set it down there, without its arm running
        into the robot's body (IK trials, one pose after the other)."""
        above, at = self.pick_poses(obj, heading)
        R = grasps.R_world_palm_down(heading)
        over_goal = grasps.T_world_hand_pinching(np.add(goal, [0, 0, 0.12]), R)
        at_goal = grasps.T_world_hand_pinching(goal, R)
        a, b = above.translation(), over_goal.translation()
        way = [
            mink.SE3.from_rotation_and_translation(above.rotation(), a + k / CARRY_CHECKS * (b - a))
            for k in range(1, CARRY_CHECKS)
        ]
        return self.reaches(effector, [above, at, above, *way, over_goal, at_goal])

    def transfer(
        self,
        obj: str,
        goal_centre,
        symmetry: float | None,
        effector: str | None = None,
        slack: float = 0.0,
    ) -> Iterator[Move]:
        """Pick ``obj`` and put it down with its centre at ``goal_centre`` (world), with
        ``effector`` or else the hand nearest the object that reaches both it and the goal;
        relayed through another hand when none does (:meth:`relay_point`).

        ``slack`` (m): how far from ``goal_centre`` the object may end (inside a target
        area); a hand that cannot reach the goal itself tries points up to that much nearer
        its arm's base before the next hand is tried.
        """
        start = self.task.objects[obj].pos(self.env.data)
        centre = np.asarray(goal_centre, float)
        order = [effector] if effector is not None else self.effectors_by_distance(start)
        for hand in order:
            heading = self.heading_for(obj, symmetry, hand)
            goal = next(
                (g for g in self.goals_towards(hand, centre, slack)
                 if self.reaches_to_carry(hand, obj, heading, g)),
                None,
            )  # fmt: skip
            if goal is not None:
                break
        else:
            hand, heading, goal = order[0], self.heading_for(obj, symmetry, order[0]), centre
            takers = [
                n
                for n in self.effector_names
                if n != hand and self.reaches_to_place(n, goal, self.pinch_heading(n))
            ]
            if takers:
                relay = self.relay_point(obj, start, goal, hand, takers[0], heading)
                yield from self.pick(hand, obj, heading)
                yield from self.place(hand, relay, held=obj)
                # The giver withdraws while the taker reaches over the object.
                hand, giver = takers[0], hand
                heading = self.heading_for(obj, symmetry, hand)
                yield from self.pick(hand, obj, heading, also=self.ready_poses_of(giver))
                yield from self.place(hand, goal, held=obj)
                yield from self.retreat(hand)
                return
        yield from self.pick(hand, obj, heading)
        yield from self.place(hand, goal, held=obj)
        yield from self.retreat(hand)

    def goals_towards(self, effector: str, centre: np.ndarray, slack: float) -> list[np.ndarray]:
        """``centre``, then points up to ``slack`` from it towards ``effector``'s arm base."""
        base = np.asarray(self.effector_spec(effector).base_pos[:2], float)
        towards = base - centre[:2]
        towards /= max(float(np.linalg.norm(towards)), 1e-9)
        return [
            np.array([*(centre[:2] + shift * towards), centre[2]])
            for shift in np.linspace(0.0, slack, GOAL_STEPS if slack > 0 else 1)
        ]

    def effectors_by_distance(self, xy) -> list[str]:
        """Effector names, the one whose arm base is nearest ``xy`` first."""
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        return sorted(bases, key=lambda n: float(np.linalg.norm(bases[n] - np.asarray(xy[:2]))))

    def relay_point(
        self, obj: str, start, goal, giver: str, taker: str, heading: float
    ) -> np.ndarray:
        """Where ``giver`` (holding ``obj`` at ``heading``) sets it down for ``taker``: where
        the way from ``start`` to ``goal`` crosses the line midway between the two arms' bases
        (at the object's resting height), or else the point nearest there (RELAY_OFFSETS)
        that is in the workspace, clear of the other objects, and that the giver reaches to
        set the object down and the taker to pick it up."""
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        a, b = bases[giver], bases[taker]
        normal = (b - a) / np.linalg.norm(b - a)
        along = np.array([-normal[1], normal[0]])
        mid = (a + b) / 2
        d_start = float(np.dot(start[:2] - mid, normal))
        d_goal = float(np.dot(goal[:2] - mid, normal))
        s = d_start / (d_start - d_goal) if d_start * d_goal < 0 else 0.5
        crossing = start[:2] + s * (goal[:2] - start[:2])
        others = [
            (o.pos(self.env.data)[:2], self.footprint(name))
            for name, o in self.task.objects.items()
            if name != obj
        ]
        radius = self.footprint(obj)
        ws = self.task.workspace
        candidates = sorted(
            (crossing + u * along + v * normal for u in RELAY_OFFSETS for v in RELAY_OFFSETS),
            key=lambda p: float(np.linalg.norm(p - crossing)),
        )
        R_taker = grasps.R_world_palm_down(self.pinch_heading(taker))
        for p in candidates:
            point = np.array([*p, start[2]])
            if (
                all(
                    lo + radius <= v <= hi - radius
                    for v, (lo, hi) in zip(p, (ws.x, ws.y), strict=True)
                )
                and all(np.linalg.norm(p - q) >= radius + r + RELAY_GAP for q, r in others)
                and self.reaches_to_place(giver, point, heading)
                and self.reaches(
                    taker,
                    [grasps.T_world_hand_pinching(point + [0, 0, h], R_taker) for h in (0.12, 0.0)],
                )
            ):
                return point
        return np.array([*crossing, start[2]])

    def footprint(self, obj: str) -> float:
        """The radius of a circle about ``obj``'s centre that holds it (its bounding sphere)."""
        model = self.env.model
        return float(max(model.geom_rbound[g] for g in self.task.objects[obj].geom_ids))


class PickupBoxExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        box = self.task.objects["box"].pos(self.env.data)
        target = self.task.fixtures["target"].pos(self.env.data)
        yield from self.transfer(
            "box", (target[0], target[1], box[2]), np.pi / 2, slack=area_slack(BOX_AREA_HALF)
        )


class PickPlaceExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:
        item = self.task.objects["item"].pos(self.env.data)
        target = self.task.fixtures["target"].pos(self.env.data)
        yield from self.transfer(
            "item", (target[0], target[1], item[2]), None, slack=area_slack(ITEM_AREA_HALF)
        )


class StackBlocksExpert(PickAndPlaceExpert):
    def script(self) -> Iterator[Move]:

        data = self.env.data
        target = self.task.fixtures["target"].pos(data)
        large = self.task.objects["large_block"].pos(data)
        yield from self.transfer(
            "large_block",
            (target[0], target[1], large[2]),
            np.pi / 2,
            slack=area_slack(STACK_AREA_HALF),
        )
        large = self.task.objects["large_block"].pos(data)
        on_top = large + [0.0, 0.0, LARGE_HALF + SMALL_HALF]
        yield from self.transfer("small_block", on_top, np.pi / 2)
