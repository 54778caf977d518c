"""Scripted expert for Tape: middle and ring fingers down into the roll's hole, spread them
against its inner wall, lift, set the roll on the box, close the fingers, pull out.

With the palm down, the middle and ring fingers bend 90 degrees at the knuckle to point
down (together 6.8 cm wide: they fit the 7.6 cm hole side by side); the index finger stays
straight, above the roll, and the thumb out to the side. Spreading the two fingers apart
presses them on opposite sides of the inner wall, and the roll hangs on them.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert
from beavr_sim.tasks import tape as tape_task
from beavr_sim.workcell import TABLE_TOP_Z

#: The roll's centre in the hand frame with the two fingers in its hole, tips 6 mm above the
#: roll's underside (measured in the twin: tips at hand x = 0.132, fingers at y -0.015, -0.06).
ROLL_IN_HAND = np.array([0.1255, -0.0375, 0.105])
_KNUCKLES_DOWN = np.zeros(16)
_KNUCKLES_DOWN[[5, 9]] = 1.57  # middle and ring MCP
#: Fingers in, together.
FINGERS_DOWN = _KNUCKLES_DOWN
#: Fingers in, spread apart (middle abduction towards +y, ring towards -y).
FINGERS_SPREAD = _KNUCKLES_DOWN.copy()
FINGERS_SPREAD[[4, 8]] = (-0.35, 0.35)
OPEN = np.zeros(16)


class TapeExpert(ScriptedExpert):
    def script(self) -> Iterator[Move]:
        effector = self.effector_names[0]
        data = self.env.data
        roll = self.task.objects["tape"].pos(data)
        R = grasps.R_world_palm_down(0.0)

        def roll_at(p, height=0.0, in_hand=ROLL_IN_HAND):
            return grasps.T_world_hand_pinching(np.asarray(p) + [0, 0, height], R, in_hand)

        yield Move(
            poses={effector: roll_at(roll, 0.08)}, fingers={effector: FINGERS_DOWN}, settle=0.2
        )
        yield Move(poses={effector: roll_at(roll)}, settle=0.3)
        yield Move(fingers={effector: FINGERS_SPREAD}, duration=0.5, settle=0.3)
        yield Move(poses={effector: roll_at(roll, 0.10)}, settle=0.4)

        box = self.task.fixtures["box"].pos(data)
        goal = np.array(
            [box[0], box[1], TABLE_TOP_Z + 2 * tape_task.BOX_HALF[2] + tape_task.TAPE_HALF_WIDTH]
        )
        in_hand = self.object_in_hand(effector, "tape")
        yield Move(poses={effector: roll_at(goal, 0.06, in_hand)}, settle=0.3)
        yield Move(poses={effector: roll_at(goal, 0.003, in_hand)}, settle=0.3)
        yield Move(fingers={effector: FINGERS_DOWN}, duration=0.4, settle=0.2)
        yield Move(poses={effector: roll_at(goal, 0.10, in_hand)})
        yield Move(fingers={effector: OPEN}, duration=0.4)
        yield from self.retreat(effector)
