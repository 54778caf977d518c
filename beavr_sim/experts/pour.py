"""Scripted expert for Pour: pinch the paper cup, carry it beside the target cup and roll the
wrist so the drops pour out over the target's rim.

The cup is front-pinched around its body (see :mod:`beavr_sim.experts.grasps`), lifted and
carried to a pouring pose: its pinch centre beside the target cup, on the side of the pouring
arm's base, and above the target's rim. There the hand rolls about the finger axis (world x
at heading 0) by ``POUR_ANGLE``, which tips the cup's mouth sideways and down towards the
target; it holds while the drops run out (success ends the episode), then rolls back and sets
the cup down where it stood.
"""

from __future__ import annotations

from collections.abc import Iterator

import mink
import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert
from beavr_sim.robots.embodiment import TABLE_TOP_Z

#: Pinch centre height above the table when grasping the cup (its body centre is at 4 cm).
PINCH_HEIGHT = 0.045
#: Wrist roll (rad, about the finger axis) that tips the cup's mouth towards the target.
POUR_ANGLE = np.deg2rad(120.0)
#: Pinch centre of the tipped cup relative to the target cup's base centre: sideways (towards
#: the pouring arm's base) and up.
POUR_SIDE = 0.06
POUR_UP = 0.15
POUR_HOLD = 1.5


class PourExpert(ScriptedExpert):
    def nearest_effector(self, xy) -> str:
        bases = {e.name: np.asarray(e.base_pos[:2]) for e in self.embodiment.spec.effectors}
        return min(bases, key=lambda n: float(np.linalg.norm(bases[n] - np.asarray(xy[:2]))))

    def script(self) -> Iterator[Move]:
        data = self.env.data
        source = self.task.objects["source_cup"].pos(data)
        target = self.task.fixtures["target_cup"].pos(data)
        effector = self.nearest_effector(source)
        spec = next(e for e in self.embodiment.spec.effectors if e.name == effector)
        side = 1.0 if spec.base_pos[1] > target[1] else -1.0

        # Pick (the cup body, not its rim).
        heading = 0.0
        R = grasps.R_world_palm_down(heading)
        centre = np.array([source[0], source[1], TABLE_TOP_Z + PINCH_HEIGHT])
        above = grasps.T_world_hand_pinching(centre + [0, 0, 0.12], R)
        yield Move(poses={effector: above}, fingers={effector: grasps.PINCH_OPEN}, settle=0.2)
        yield Move(poses={effector: grasps.T_world_hand_pinching(centre, R)}, settle=0.2)
        yield Move(fingers={effector: grasps.PINCH_CLOSED}, duration=0.6, settle=0.3)
        yield Move(poses={effector: above}, settle=0.2)

        # Carry beside the target and tip.
        pour_at = target + [0.0, side * POUR_SIDE, POUR_UP]
        yield Move(poses={effector: grasps.T_world_hand_pinching(pour_at, R)}, settle=0.2)
        roll = -side * POUR_ANGLE
        R_tipped = R @ mink.SO3.from_z_radians(roll).as_matrix()
        yield Move(poses={effector: grasps.T_world_hand_pinching(pour_at, R_tipped)})
        yield Move(settle=POUR_HOLD)
        yield Move(poses={effector: grasps.T_world_hand_pinching(pour_at, R)}, settle=0.2)
