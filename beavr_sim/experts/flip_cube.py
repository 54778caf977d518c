"""Scripted expert for FlipCube: pinch the cube, lift it, roll the wrist a quarter turn so
a side face comes up, lower it and let go just above the table.

The roll is about the finger axis with the hand's fingers ending up stacked vertically; the
lowest finger then reaches ``LOWEST_FINGER_BELOW_PINCH`` below the pinch centre, so the cube
is released with that finger ``RELEASE_CLEARANCE`` above the table (a drop of a few cm onto
a face, like a person letting a cube go).
"""

from __future__ import annotations

from collections.abc import Iterator

import mink
import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert
from beavr_sim.workcell import TABLE_TOP_Z

#: How far the lowest finger of the rolled hand hangs below the pinch centre (measured).
LOWEST_FINGER_BELOW_PINCH = 0.065
RELEASE_CLEARANCE = 0.01
#: Wrist roll (rad, about the finger axis) that turns the palm from down to sideways with
#: the fingers' short side (+y of the hand frame) down.
ROLL = -np.pi / 2


class FlipCubeExpert(ScriptedExpert):
    def script(self) -> Iterator[Move]:
        effector = self.effector_names[0]
        cube = self.task.objects["cube"]
        R = cube.R_world_body(self.env.data)
        # The cube's body axis closest to horizontal-and-forward gives a face-to-face pinch.
        horizontal = [k for k in range(3) if abs(R[2, k]) < 0.5]
        yaw = float(np.arctan2(R[1, horizontal[0]], R[0, horizontal[0]]))
        heading = grasps.fold_heading(yaw, np.pi / 2)
        yield from self.pick(effector, "cube", heading, lift=0.1)

        R_rolled = grasps.R_world_palm_down(heading) @ mink.SO3.from_z_radians(ROLL).as_matrix()
        xy = cube.pos(self.env.data)[:2]
        z_release = TABLE_TOP_Z + LOWEST_FINGER_BELOW_PINCH + RELEASE_CLEARANCE
        up = grasps.T_world_hand_pinching((*xy, z_release + 0.08), R_rolled)
        yield Move(poses={effector: up}, settle=0.2)
        low = grasps.T_world_hand_pinching((*xy, z_release), R_rolled)
        yield Move(poses={effector: low}, settle=0.3)
        yield Move(fingers={effector: grasps.RELEASE}, duration=0.4, settle=0.3)
        yield Move(poses={effector: up})
        yield from self.retreat(effector)
