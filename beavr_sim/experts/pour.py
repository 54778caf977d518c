"""Scripted expert for Pour: pinch the paper cup, hold it over the edge of the target cup and
roll the wrist so that the drops run out over the lip into the target.

The cup is front-pinched around its body (see :mod:`beavr_sim.experts.grasps`) by the hand
whose arm base is nearest it, and lifted. The expert then looks where the cup sits in the hand
and plans with that: it carries the cup upright beside the target so that the lip on the
pouring side hangs over the target's opening, the cup's bottom clear above the target's rim,
and tips the cup by ``POUR_ANGLE`` about the finger axis, pivoting about that lip as a person
does. The pouring side is the hand's little-finger side (away from the thumb): the palm covers
the cup's mouth in a front pinch, and on that side the drops fall clear of the hand. After the
drops have run out (success ends the episode) it rolls back and sets the cup down.
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
from beavr_sim.robots.embodiment import TABLE_TOP_Z
from beavr_sim.tasks.pour import (
    SOURCE_HEIGHT,
    SOURCE_OUTER_RADIUS,
    TARGET_HEIGHT,
    TARGET_INNER_RADIUS,
)

#: Pinch centre height above the table when grasping the cup (its body centre is at 4 cm).
PINCH_HEIGHT = 0.045
LIFT = 0.12
#: Tip of the cup about the finger axis (rad) when pouring.
POUR_ANGLE = np.deg2rad(120.0)
#: The pouring lip, before tipping: this far inside the target's inner wall (horizontally)...
LIP_INSIDE = 0.015
#: ... and the cup's bottom this far above the target's rim.
BOTTOM_CLEARANCE = 0.015
POUR_HOLD = 1.5


@dataclass
class Tilt(Move):
    """Rotate ``effector``'s hand (and what it holds) by ``angle`` about the world ``axis``
    through the world point ``pivot``: the pivot stays still during the whole motion."""

    effector: str = ""
    pivot: np.ndarray | None = None
    axis: np.ndarray | None = None
    angle: float = 0.0


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
        side = next(e.side for e in self.embodiment.spec.effectors if e.name == effector)

        # Pick the cup by its body.
        heading = 0.0
        R = grasps.R_world_palm_down(heading)
        centre = np.array([source[0], source[1], TABLE_TOP_Z + PINCH_HEIGHT])
        above = grasps.T_world_hand_pinching(centre + [0, 0, LIFT], R)
        yield Move(poses={effector: above}, fingers={effector: grasps.PINCH_OPEN}, settle=0.2)
        yield Move(poses={effector: grasps.T_world_hand_pinching(centre, R)}, settle=0.2)
        yield Move(fingers={effector: grasps.PINCH_CLOSED}, duration=0.6, settle=0.3)
        yield Move(poses={effector: above}, settle=0.3)

        # Where the cup sits in the hand; the pour direction: the hand's little-finger side.
        cup_in_hand = self.object_in_hand(effector, "source_cup")
        axis = np.array([np.cos(heading), np.sin(heading), 0.0])  # fingers
        towards = np.cross(axis, [0.0, 0.0, 1.0])  # tipping +angle about axis leans this way
        angle = POUR_ANGLE if side == "right" else -POUR_ANGLE
        pour_dir = towards if angle > 0 else -towards
        # Upright cup beside the target, its pouring lip over the target's opening.
        lip_xy = target[:2] - pour_dir[:2] * (TARGET_INNER_RADIUS - LIP_INSIDE)
        base_z = target[2] + TARGET_HEIGHT + BOTTOM_CLEARANCE
        cup_pos = np.array([*(lip_xy - pour_dir[:2] * SOURCE_OUTER_RADIUS), base_z])
        lip = np.array([*lip_xy, base_z + SOURCE_HEIGHT])
        T_hand = mink.SE3.from_rotation_and_translation(
            mink.SO3.from_matrix(R), cup_pos - R @ cup_in_hand
        )
        yield Move(poses={effector: T_hand}, settle=0.3)
        yield Tilt(effector=effector, pivot=lip, axis=axis, angle=angle, settle=POUR_HOLD)
        yield Tilt(effector=effector, pivot=lip, axis=axis, angle=-angle, settle=0.2)
