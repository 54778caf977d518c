"""PickPlace: pick up an item and place it in the marked target area.

Objects: the item, a food tin (cylinder 6 cm across, 8 cm tall, 150 g) standing upright; a
blue 12 x 12 cm target area. Reset: item and area centres uniform in the workspace, at least
3 cm apart (footprints), area yaw uniform in +-30 degrees. With two arms the area's centre
lies in the middle band (TabletopTask.SHARED_TARGET_HALF_BAND, 8 cm), where both hands reach.

Success: the item was lifted (its centre rose >= 5 cm above its resting height: the
``lifted`` latch) and now its centre is inside the target area, it stands upright (tilt
< 15 degrees) on the table, the robot no longer touches it and it has been at rest
(checks.REST_*): an item in the area but still sliding is not a success.
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.checks import RestTimer, in_contact, inside_rectangle, up_axis_tilt
from beavr_sim.tasks.objects import add_free_body, add_target_area, geom_kwargs, yaw_quat
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

ITEM_RADIUS = 0.03
ITEM_HALF_HEIGHT = 0.04
ITEM_MASS = 0.15
AREA_HALF = (0.06, 0.06)
LIFT_HEIGHT = 0.05
MAX_TILT = np.deg2rad(15.0)


class PickPlace(TabletopTask):
    name = "PickPlace"
    instruction = "Pick up the tin and place it in the blue area."
    max_episode_seconds = 20.0
    embodiments = ("xarm7_leap_right", "xarm7_leap_bimanual", "rx1")
    object_names = ("item",)
    fixture_names = ("target",)

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        body = add_free_body(scene, "item")
        body.add_geom(
            name="item/geom",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            size=[ITEM_RADIUS, ITEM_HALF_HEIGHT, 0],
            mass=ITEM_MASS,
            **geom_kwargs((0.85, 0.2, 0.15, 1)),
        )
        add_target_area(scene, "target", AREA_HALF, rgba=(0.2, 0.4, 0.85, 1))

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        (item_xy,), area_xy = self.layout_with_target(
            rng, [ITEM_RADIUS], float(np.hypot(*AREA_HALF)), gap=0.03
        )
        self.objects["item"].set_pose(
            data, (*item_xy, TABLE_TOP_Z + ITEM_HALF_HEIGHT), yaw_quat(rng.uniform(-np.pi, np.pi))
        )
        self.fixtures["target"].place(data, area_xy, rng.uniform(-np.pi / 6, np.pi / 6))

    def reset_latches(self) -> None:
        self.lifted = False
        self.rest = RestTimer()

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        item = self.objects["item"]
        pos = item.pos(data)
        self.lifted |= bool(pos[2] >= TABLE_TOP_Z + ITEM_HALF_HEIGHT + LIFT_HEIGHT)
        at_rest = self.still(data, "item", self.rest)
        target = self.fixtures["target"]
        in_area = inside_rectangle(pos, target.pos(data), AREA_HALF, target.yaw(data))
        upright = bool(up_axis_tilt(item.R_world_body(data)) < MAX_TILT)
        on_table = in_contact(model, data, item.geom_ids, self.table_geoms)
        released = not self.touched_by_robot(model, data, "item")
        success = self.lifted and in_area and upright and on_table and released and at_rest
        return TaskStatus(
            success=success,
            details={
                "lifted": self.lifted,
                "in_area": in_area,
                "upright": upright,
                "on_table": on_table,
                "released": released,
                "at_rest": at_rest,
            },
        )
