"""Scripted expert for Lantern: hook the middle finger under the bail handle, carry the
lantern hanging from it, set it on the box, unhook.

The hook: the hand palm down with its fingers across the handle bar, the bar just under
the middle finger's proximal phalanx (``BAR_IN_HAND``). The middle finger first bends its
distal joint, then its middle joint, so its tip sweeps an arc in front of and then under the
bar without reaching down to the lantern's cap; the other fingers stay straight above the
bar, the thumb out to the side.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from beavr_sim.experts import grasps
from beavr_sim.experts.base import Move, ScriptedExpert
from beavr_sim.tasks import lantern as lantern_task
from beavr_sim.workcell import TABLE_TOP_Z

#: Where the bar's centre sits in the hand frame when the hook closes (measured in the twin).
BAR_IN_HAND = np.array([0.028, -0.015, 0.132])
#: Middle finger (joints 4-7: spread, MCP, PIP, DIP) curled into a hook; all else straight.
HOOK = np.zeros(16)
HOOK[6:8] = (1.5, 1.5)
#: The hook's first stage: only the distal joint bent.
HOOK_DISTAL = np.zeros(16)
HOOK_DISTAL[7] = 1.5
OPEN = np.zeros(16)
#: Bar height above the lantern's centre.
BAR_ABOVE_CENTRE = (
    lantern_task.LANTERN_HALF_HEIGHT + lantern_task.HANDLE_CLEARANCE + lantern_task.HANDLE_RADIUS
)


class LanternExpert(ScriptedExpert):
    def script(self) -> Iterator[Move]:
        effector = self.effector_names[0]
        data = self.env.data
        lantern = self.task.objects["lantern"]
        R_world_lantern = lantern.R_world_body(data)
        bar_yaw = float(np.arctan2(R_world_lantern[1, 0], R_world_lantern[0, 0]))
        # Fingers across the bar; the bar looks the same after a half turn.
        heading = grasps.fold_heading(bar_yaw + np.pi / 2, np.pi)
        R = grasps.R_world_palm_down(heading)
        bar = lantern.pos(data) + [0.0, 0.0, BAR_ABOVE_CENTRE]

        def bar_at(p, height=0.0, in_hand=BAR_IN_HAND):
            return grasps.T_world_hand_pinching(np.asarray(p) + [0, 0, height], R, in_hand)

        yield Move(poses={effector: bar_at(bar, 0.08)}, fingers={effector: OPEN}, settle=0.2)
        yield Move(poses={effector: bar_at(bar)}, settle=0.3)
        yield Move(fingers={effector: HOOK_DISTAL}, duration=0.4, settle=0.1)
        # Hold still until the hook has closed: the fingers close at the LEAP servos' torque
        # cap (docs/models.md), and a hand that lifts early slides off the bar.
        yield Move(fingers={effector: HOOK}, duration=0.6, settle=0.8)
        yield Move(poses={effector: bar_at(bar, 0.10)}, settle=0.5)

        # Carry: aim with where the lantern really hangs (it may swing a little in the hook).
        box = self.task.fixtures["box"].pos(data)
        box_top = TABLE_TOP_Z + 2 * lantern_task.BOX_HALF[2]
        goal_bar = np.array([box[0], box[1], box_top + lantern_task.LANTERN_HALF_HEIGHT])
        goal_bar[2] += BAR_ABOVE_CENTRE
        in_hand = self.object_in_hand(effector, "lantern") + R.T @ [0, 0, BAR_ABOVE_CENTRE]
        yield Move(poses={effector: bar_at(goal_bar, 0.06, in_hand)}, settle=0.4)
        yield Move(poses={effector: bar_at(goal_bar, 0.003, in_hand)}, settle=0.3)
        yield Move(fingers={effector: HOOK_DISTAL}, duration=0.4)
        yield Move(fingers={effector: OPEN}, duration=0.4, settle=0.2)
        yield Move(poses={effector: bar_at(goal_bar, 0.06, in_hand)})
        yield from self.retreat(effector)
