"""PickupBox: grasp a small box, lift it, set it down in the target area.

Objects: a cardboard box 5.5 x 5.5 x 7 cm, 80 g, standing upright; a 14 x 14 cm target area.
Reset: box and area centres uniform in the workspace, footprints at least 3 cm apart, box yaw
uniform in +-45 degrees.

Success: the box was lifted (its centre rose >= 5 cm above its resting height at some point:
the ``lifted`` latch), and now its centre is inside the target area, it stands on the table
(touching it, not the robot) and it has been at rest (checks.REST_*).
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.checks import RestTimer, in_contact, inside_rectangle
from beavr_sim.tasks.objects import add_box_object, add_target_area, yaw_quat
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

BOX_HALF = (0.0275, 0.0275, 0.035)
BOX_MASS = 0.08
AREA_HALF = (0.07, 0.07)
LIFT_HEIGHT = 0.05


class PickupBox(TabletopTask):
    name = "PickupBox"
    instruction = "Pick up the box and put it down in the green area."
    max_episode_seconds = 20.0
    embodiments = ("xarm7_leap_right", "rx1")
    object_names = ("box",)
    fixture_names = ("target",)

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        add_box_object(scene, "box", BOX_HALF, BOX_MASS, rgba=(0.78, 0.6, 0.38, 1))
        add_target_area(scene, "target", AREA_HALF, rgba=(0.2, 0.75, 0.3, 1))

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        box_xy, area_xy = self.workspace.sample_layout(
            rng, [float(np.hypot(*BOX_HALF[:2])), float(np.hypot(*AREA_HALF))], gap=0.03
        )
        yaw = rng.uniform(-np.pi / 4, np.pi / 4)
        self.objects["box"].set_pose(data, (*box_xy, TABLE_TOP_Z + BOX_HALF[2]), yaw_quat(yaw))
        self.fixtures["target"].place(data, area_xy)

    def reset_latches(self) -> None:
        self.lifted = False
        self.rest = RestTimer()

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        box = self.objects["box"]
        pos = box.pos(data)
        self.lifted |= bool(pos[2] >= TABLE_TOP_Z + BOX_HALF[2] + LIFT_HEIGHT)
        at_rest = self.still(data, "box", self.rest)
        target = self.fixtures["target"]
        in_area = inside_rectangle(pos, target.pos(data), AREA_HALF, target.yaw(data))
        on_table = in_contact(model, data, box.geom_ids, self.table_geoms)
        released = not self.touched_by_robot(model, data, "box")
        success = self.lifted and in_area and on_table and released and at_rest
        return TaskStatus(
            success=success,
            details={
                "lifted": self.lifted,
                "in_area": in_area,
                "on_table": on_table,
                "released": released,
                "at_rest": at_rest,
            },
        )
