"""Scripted expert for Pour: pinch the paper cup, hold it over the target cup and roll the
wrist so that the drops run out over the lip into the target.

The cup is front-pinched around its body (see :mod:`beavr_sim.experts.grasps`) by the hand
whose arm base is nearest it, with a firmer squeeze than the standard pinch (``PINCH_FIRM``;
the thumb closes first, as a backstop, then the fingers), and lifted. The hand holds it at the
arm's pour heading (:meth:`ArmModel.pour_heading`: fingers straight ahead on an xArm7), from
which the arm can roll the hand over; if its fingers would come down on the target cup there,
it pinches at the nearest heading that keeps them clear and turns the cup on the way. The expert then looks
where the cup sits in the hand and plans with that: it carries the cup upright (tilting the
hand a little if the cup leans in the pinch) to beside the target, its bottom clear above the
target's rim and its pouring lip over the target's axis, and tips it by ``POUR_ANGLE`` about a
horizontal axis along the fingers, pivoting about that lip as a person does (``Tilt``, a
primitive of this module). The pouring side is the hand's thumb side: the palm covers the
cup's mouth in a front pinch and the ring finger lies along the cup's other side, where the
drops would run onto it. With the fingers straight ahead, the right hand therefore pours
from the target's -y side towards +y, the left hand from its +y side towards -y. Once the drops have run out (success ends the
episode) it rolls back, sets the cup down where it stood, lets go and withdraws.

The left hand's pinch draws the cup a few cm towards the wrist as it closes (the right's does
not); it is aimed ``GRASP_SHIFT`` further back to end with a comparable hold.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import mink
import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import (
    MAX_ANGULAR_SPEED,
    MAX_LINEAR_SPEED,
    Move,
    ScriptedExpert,
    smoothstep,
)
from beavr_sim.tasks.pour import (
    SOURCE_HEIGHT,
    SOURCE_OUTER_RADIUS,
    TARGET_HEIGHT,
    TARGET_OUTER_RADIUS,
)
from beavr_sim.workcell import TABLE_TOP_Z

#: Pinch centre height above the table when grasping the cup (its body centre is at 4 cm).
PINCH_HEIGHT = 0.045
LIFT = 0.15
#: Tip of the cup about the finger axis (rad) when pouring.
POUR_ANGLE = np.deg2rad(110.0)
#: The pouring lip, before tipping: this far past the target's axis (horizontally, in the
#: pour direction)...
LIP_OFFSET = 0.0
#: ... and the cup's bottom this far above the target's rim.
BOTTOM_CLEARANCE = 0.02
TILT_SECONDS = 2.5
POUR_HOLD = 1.5
#: A firmer pinch than grasps.PINCH_CLOSED, per hand side: the tipped cup must not turn in the
#: fingers. The thumb's third joint (motor 14) closes to 0.8 rad on the right, 1.0 on the left
#: (1.2 before the hand got the real servos' torque cap, docs/models.md "LEAP servos"): with
#: the thumb as strong as each finger, a thumb aimed at 1.2 pushes the cup out along the fingers,
#: away from the palm, and the tipped cup pours onto the hand (right hand: 0/10 episodes). The
#: left hand's pinch (see GRASP_SHIFT) holds the cup best at 1.0.
PINCH_FIRM = {
    side: grasps.finger_shape(1.0, 1.0, 0.5, (1.6, 0.6, thumb, 0.8))
    for side, thumb in (("right", 0.8), ("left", 1.0))
}
#: Where the pinch centre is aimed, along the fingers from the cup's axis (m), per hand side.
GRASP_SHIFT = {"right": 0.0, "left": -0.02}
#: The thumb closes first, a backstop on the near side, then the fingers. Its tip rests on the
#: table and presses there as it curls, which pins it (THUMB_FIRST) where the arm holds the
#: hand still; where the arm gives way (:attr:`ArmModel.holds_against_fingertips`), the tip
#: slips in under the cup and shoves it along the fingers, so its joint stays open in that
#: step (THUMB_FIRST_TIP_OPEN).
THUMB_FIRST = {s: np.concatenate([grasps.PINCH_OPEN[:12], f[12:]]) for s, f in PINCH_FIRM.items()}
THUMB_FIRST_TIP_OPEN = {
    s: np.concatenate([f[:15], grasps.PINCH_OPEN[15:]]) for s, f in THUMB_FIRST.items()
}
#: Each closing step takes this long: slow enough for the thumb to land on the cup.
CLOSE_SECONDS = 1.0
#: The open pinch's fingertips reach this far past the cup's axis (along the fingers) and
#: this far to either side of it (m): the target cup must not stand there when the hand
#: comes down on the source cup.
FINGER_REACH = 0.10
FINGER_HALF_WIDTH = 0.055
#: Turns of the grasp heading (deg, either way) tried in turn to keep the fingers clear.
GRASP_TURN_STEPS_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)


@dataclass
class Tilt(Move):
    """Rotate ``effector``'s hand (and what it holds) by ``angle`` about the world ``axis``
    through the world point ``pivot``: the pivot stays still during the whole motion."""

    effector: str = ""
    pivot: np.ndarray | None = None
    axis: np.ndarray | None = None
    angle: float = 0.0


@dataclass(frozen=True)
class PourPlan:
    """A pour with one hand heading: ``R_grasp`` / ``grasp_centre``, the hand's orientation and
    pinch centre on the cup; ``base``, the cup's base centre upright before the pour; ``lip``,
    the pivot (its pouring lip then); ``axis``, what it tips about (world)."""

    R_grasp: np.ndarray
    grasp_centre: np.ndarray
    base: np.ndarray
    lip: np.ndarray
    axis: np.ndarray


def rotated_about(T: mink.SE3, pivot, axis, angle: float) -> mink.SE3:
    """Pose ``T`` rotated by ``angle`` about the world ``axis`` through ``pivot``."""
    R = mink.SO3.exp(np.asarray(axis, float) * angle)
    pivot = np.asarray(pivot, float)
    return mink.SE3.from_rotation_and_translation(
        R @ T.rotation(), pivot + R.as_matrix() @ (T.translation() - pivot)
    )


class PourExpert(ScriptedExpert):
    def nearest_effector(self, xy) -> str:
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        return min(bases, key=lambda n: float(np.linalg.norm(bases[n] - np.asarray(xy[:2]))))

    def _expand(self, move: Move) -> list[tuple[dict, dict]]:
        if not isinstance(move, Tilt):
            return super()._expand(move)
        start = self.pose[move.effector]
        reach = np.linalg.norm(start.translation() - move.pivot)
        duration = max(
            move.duration,
            abs(move.angle) / MAX_ANGULAR_SPEED,
            abs(move.angle) * reach / MAX_LINEAR_SPEED,
        )
        n = max(1, int(np.ceil(duration / self.dt)))
        fingers = dict(self.fingers)
        steps = [
            (
                {
                    **self.pose,
                    move.effector: rotated_about(
                        start, move.pivot, move.axis, smoothstep(i / n) * move.angle
                    ),
                },
                fingers,
            )
            for i in range(1, n + 1)
        ]
        return steps + [steps[-1]] * int(np.ceil(move.settle / self.dt))

    def T_world(self, body: str) -> mink.SE3:
        b = self.env.data.body(body)
        return mink.SE3.from_rotation_and_translation(
            mink.SO3.from_matrix(b.xmat.reshape(3, 3)), b.xpos.copy()
        )

    def script(self) -> Iterator[Move]:
        data = self.env.data
        source = self.task.objects["source_cup"].pos(data)
        target = self.task.fixtures["target_cup"].pos(data)
        effector = self.nearest_effector(source)
        heading = self.pour_heading(effector)
        grasp_heading = self.grasp_heading(effector, source, target, heading)
        plan = self.plan(effector, grasp_heading, heading, source, target)

        # Pick the cup by its body.
        R, centre = plan.R_grasp, plan.grasp_centre
        above = grasps.T_world_hand_pinching(centre + [0, 0, LIFT], R)
        yield Move(poses={effector: above}, fingers={effector: grasps.PINCH_OPEN}, settle=0.2)
        yield Move(poses={effector: grasps.T_world_hand_pinching(centre, R)}, settle=0.2)
        for shape in self.close_sequence(effector):
            yield Move(fingers={effector: shape}, duration=CLOSE_SECONDS, settle=0.1)
        yield Move(settle=0.2)
        yield Move(poses={effector: above}, settle=0.3)

        # The cup upright beside the target, its pouring lip over the target's opening, its
        # bottom clear above the target's rim; the hand pose from where the cup sits in it.
        # A hand that took the cup at another heading turns to the pour's on the way (the cup
        # turns about its own axis), and back to set it down.
        turned = grasp_heading != heading
        to_pour, to_grasp = (heading, grasp_heading) if turned else (None, None)
        base, lip, axis = plan.base, plan.lip, plan.axis
        yield Move(poses={effector: self.hand_for_cup(effector, base, to_pour)}, settle=0.3)
        # Look again (the cup may have shifted in the pinch during the carry) and correct.
        yield Move(poses={effector: self.hand_for_cup(effector, base, to_pour)}, settle=0.2)
        yield Tilt(
            effector=effector,
            pivot=lip,
            axis=axis,
            angle=POUR_ANGLE,
            duration=TILT_SECONDS,
            settle=POUR_HOLD,
        )
        yield Tilt(
            effector=effector, pivot=lip, axis=axis, angle=-POUR_ANGLE, duration=TILT_SECONDS
        )
        # Put the cup back down where it stood and let go.
        home = np.array([source[0], source[1], TABLE_TOP_Z])
        for height, settle in ((LIFT, 0.2), (0.005, 0.2)):
            yield Move(
                poses={effector: self.hand_for_cup(effector, home + [0, 0, height], to_grasp)},
                settle=settle,
            )
        yield Move(fingers={effector: grasps.RELEASE}, duration=0.4, settle=0.2)
        released = self.pose[effector]
        up = mink.SE3.from_rotation_and_translation(
            released.rotation(), released.translation() + [0.0, 0.0, 0.1]
        )
        yield Move(poses={effector: up})
        yield from self.retreat(effector)

    def close_sequence(self, effector: str) -> tuple[np.ndarray, ...]:
        """The finger shapes that close ``effector``'s hand on the cup, in turn."""
        spec = self.effector_spec(effector)
        first = THUMB_FIRST if spec.arm.holds_against_fingertips else THUMB_FIRST_TIP_OPEN
        return (first[spec.side], PINCH_FIRM[spec.side])

    def pour_heading(self, effector: str) -> float:
        """The hand heading (rad, world) to pinch the cup with: the one from which the arm
        tips it over the target (:meth:`ArmModel.pour_heading`, turned with the base)."""
        e = self.effector_spec(effector)
        return e.arm.pour_heading(e.side) + float(np.deg2rad(e.base_yaw_deg))

    def grasp_heading(self, effector: str, source, target, heading: float) -> float:
        """The hand heading to pinch the cup with: ``heading`` (the pour's), unless the open
        fingers, which reach FINGER_REACH past the cup, would run into the target cup; then
        the heading nearest it that keeps them clear (turning towards the arm's pinch heading
        first)."""
        ahead = np.asarray(target[:2], float) - np.asarray(source[:2], float)
        reference = self.pinch_heading(effector)
        for step in np.deg2rad(GRASP_TURN_STEPS_DEG):
            for h in sorted({heading + step, heading - step}, key=lambda h: abs(h - reference)):
                along = ahead @ [np.cos(h), np.sin(h)]
                across = ahead @ [-np.sin(h), np.cos(h)]
                if not (
                    -TARGET_OUTER_RADIUS < along < FINGER_REACH + TARGET_OUTER_RADIUS
                    and abs(across) < FINGER_HALF_WIDTH + TARGET_OUTER_RADIUS
                ):
                    return float(h)
        return heading

    def plan(self, effector: str, grasp_heading: float, heading: float, source, target) -> PourPlan:
        """Where to pinch the cup with the hand at ``grasp_heading``, and where it pours from
        with the hand at ``heading``.

        The pour direction is the hand's thumb side (the little-finger side has the ring
        finger along the cup, where the drops would run out onto it), square to the fingers.
        """
        side = self.effector_spec(effector).side
        at_grasp = np.array([np.cos(grasp_heading), np.sin(grasp_heading), 0.0])
        centre = np.array([source[0], source[1], TABLE_TOP_Z + PINCH_HEIGHT])
        centre += GRASP_SHIFT[side] * at_grasp
        fingers = np.array([np.cos(heading), np.sin(heading), 0.0])
        thumb = 1.0 if side == "right" else -1.0
        pour_dir = thumb * np.cross([0.0, 0.0, 1.0], fingers)
        lip_xy = np.asarray(target[:2]) + pour_dir[:2] * LIP_OFFSET
        base = np.array([*(lip_xy - pour_dir[:2] * SOURCE_OUTER_RADIUS), 0.0])
        base[2] = target[2] + TARGET_HEIGHT + BOTTOM_CLEARANCE
        return PourPlan(
            R_grasp=grasps.R_world_palm_down(grasp_heading),
            grasp_centre=centre,
            base=base,
            lip=np.array([*lip_xy, base[2] + SOURCE_HEIGHT]),
            axis=np.cross([0.0, 0.0, 1.0], pour_dir),  # tipping about it leans the cup pour_dir
        )

    def hand_for_cup(self, effector: str, base, heading: float | None = None) -> mink.SE3:
        """The hand pose that puts the held cup upright with its base centre at ``base``,
        from where the cup sits in the hand now (it may have turned a little in the pinch),
        with the hand turned about the cup's axis to ``heading`` if given."""
        T_hand_cup = self.T_world(f"{effector}/hand").inverse() @ self.T_world("source_cup")
        up = T_hand_cup.rotation().as_matrix()[:, 2]
        R_hand = self.pose[effector].rotation().as_matrix()
        up_world = R_hand @ up
        R_level = rotation_between(up_world, np.array([0.0, 0.0, 1.0]))
        if heading is not None:
            fingers = R_level @ R_hand[:, 2]
            turn = heading - np.arctan2(fingers[1], fingers[0])
            R_level = mink.SO3.exp(np.array([0.0, 0.0, turn])).as_matrix() @ R_level
        R_cup = R_level @ R_hand @ T_hand_cup.rotation().as_matrix()
        T_world_cup = mink.SE3.from_rotation_and_translation(
            mink.SO3.from_matrix(R_cup), np.asarray(base, float)
        )
        return T_world_cup @ T_hand_cup.inverse()


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-9:
        return np.eye(3)
    return mink.SO3.exp(axis / s * np.arctan2(s, c)).as_matrix()
