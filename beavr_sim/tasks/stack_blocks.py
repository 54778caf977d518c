"""StackBlocks: put two blocks of different size into the target area, the smaller on top.

Objects: a large wooden block (6.5 cm cube, 165 g) and a small one (4.5 cm cube, 55 g), both
resting on the table; a yellow 14 x 14 cm target area. Reset: the three footprints uniform in
the workspace, at least 2.5 cm apart; block yaws uniform in +-45 degrees. With two arms the
target area's centre lies in the middle band (TabletopTask.SHARED_TARGET_HALF_BAND, 8 cm),
where both hands reach.

Success: the large block's centre is inside the target area and it stands on the table; the
small block rests on the large one (they touch, and the small block's centre is above the
large block's top face and within its footprint); neither touches the robot; both have been at
rest (checks.REST_*). Stacked the wrong way round is not a success.
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.checks import RestTimer, in_contact, inside_rectangle
from beavr_sim.tasks.objects import add_box_object, add_target_area, yaw_quat
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

LARGE_HALF = 0.0325
SMALL_HALF = 0.0225
LARGE_MASS = 0.165
SMALL_MASS = 0.055
AREA_HALF = (0.07, 0.07)


class StackBlocks(TabletopTask):
    name = "StackBlocks"
    instruction = "Stack the blocks in the yellow area, the small one on top of the large one."
    max_episode_seconds = 30.0
    embodiments = ("xarm7_leap_right", "xarm7_leap_bimanual", "rx1")
    object_names = ("large_block", "small_block")
    fixture_names = ("target",)

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        add_box_object(scene, "large_block", (LARGE_HALF,) * 3, LARGE_MASS, (0.25, 0.45, 0.8, 1))
        add_box_object(scene, "small_block", (SMALL_HALF,) * 3, SMALL_MASS, (0.85, 0.3, 0.25, 1))
        add_target_area(scene, "target", AREA_HALF, rgba=(0.9, 0.8, 0.2, 1))

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        (large_xy, small_xy), area_xy = self.layout_with_target(
            rng,
            [LARGE_HALF * np.sqrt(2), SMALL_HALF * np.sqrt(2)],
            float(np.hypot(*AREA_HALF)),
            gap=0.025,
        )
        for name, xy, half in (
            ("large_block", large_xy, LARGE_HALF),
            ("small_block", small_xy, SMALL_HALF),
        ):
            yaw = rng.uniform(-np.pi / 4, np.pi / 4)
            self.objects[name].set_pose(data, (*xy, TABLE_TOP_Z + half), yaw_quat(yaw))
        self.fixtures["target"].place(data, area_xy)

    def reset_latches(self) -> None:
        self.rest = {name: RestTimer() for name in self.object_names}

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        large, small = self.objects["large_block"], self.objects["small_block"]
        p_large, p_small = large.pos(data), small.pos(data)
        target = self.fixtures["target"]
        large_in_area = inside_rectangle(p_large, target.pos(data), AREA_HALF, target.yaw(data))
        large_on_table = in_contact(model, data, large.geom_ids, self.table_geoms)
        # The small block's centre in the large block's frame: above its top, inside its footprint.
        p_small_in_large = large.R_world_body(data).T @ (p_small - p_large)
        small_on_large = bool(
            in_contact(model, data, small.geom_ids, large.geom_ids)
            and p_small[2] > p_large[2] + LARGE_HALF
            and np.all(np.abs(p_small_in_large[:2]) <= LARGE_HALF)
        )
        released = not (
            self.touched_by_robot(model, data, "large_block")
            or self.touched_by_robot(model, data, "small_block")
        )
        at_rest = all([self.still(data, name, self.rest[name]) for name in self.object_names])
        success = large_in_area and large_on_table and small_on_large and released and at_rest
        return TaskStatus(
            success=success,
            details={
                "large_in_area": large_in_area,
                "large_on_table": large_on_table,
                "small_on_large": small_on_large,
                "released": released,
                "at_rest": at_rest,
            },
        )
