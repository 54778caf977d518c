"""Lantern: grasp the lantern by its handle, as if to light the way, and set it on the box.

Objects: a lantern, 250 g in all: a body 8 cm across and 12 cm tall (a 1.5 cm base and a 1 cm
cap of 8 cm diameter around a 7.2 cm glass; 230 g) and a bail handle (20 g) arching over it:
two posts at +-3.5 cm and a 7 cm top bar, wire 8 mm thick, with HANDLE_CLEARANCE = 4.5 cm
clear between the cap and the bar for a LEAP finger (3.3 cm thick at the tip) to hook under;
a 14 x 14 x 8 cm cardboard box (a fixture). The lantern's origin is the centre of its body.
Reset: lantern upright, yaw uniform in +-90 degrees (the handle is symmetric under a half
turn); box yaw uniform in +-45 degrees; centres uniform in the workspace, footprints (bounding
circles) at least 3 cm apart.

Success: the ``lifted_by_handle`` latch is set (at some step the lantern's centre was
>= LIFT_HEIGHT above its resting height on the table while the robot touched a handle geom and
no body geom), and now the lantern stands upright on the box: its +z axis within MAX_TILT of
world +z, it touches the box, its centre lies over the box top (x, y inside the box
footprint), the robot does not touch it and it has been at rest (checks.REST_*).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.checks import RestTimer, in_contact, inside_rectangle, up_axis_tilt
from beavr_sim.tasks.objects import add_fixture_box, add_free_body, geom_kwargs, yaw_quat
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

LANTERN_RADIUS = 0.04
LANTERN_HALF_HEIGHT = 0.06
GLASS_RADIUS = 0.036
BASE_HEIGHT = 0.015
CAP_HEIGHT = 0.01
BASE_MASS, GLASS_MASS, CAP_MASS = 0.09, 0.08, 0.06
HANDLE_MASS = 0.02
HANDLE_HALF_SPAN = 0.035
HANDLE_RADIUS = 0.004
HANDLE_CLEARANCE = 0.045
BOX_HALF = (0.07, 0.07, 0.04)
LIFT_HEIGHT = 0.03
MAX_TILT = math.radians(15.0)
#: Geoms named with this prefix are the handle; the other lantern geoms are its body.
HANDLE_PREFIX = "lantern/handle"


class Lantern(TabletopTask):
    name = "Lantern"
    instruction = (
        "Grasp the lantern as if to use it for illumination and place it on top of the box."
    )
    max_episode_seconds = 30.0
    embodiments = ("xarm7_leap_right",)
    object_names = ("lantern",)
    fixture_names = ("box",)

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        lantern = add_free_body(scene, "lantern")
        metal, glass = (0.12, 0.3, 0.2, 1), (0.98, 0.9, 0.6, 1)
        top = LANTERN_HALF_HEIGHT
        for part, radius, z0, z1, mass, rgba in (
            ("base", LANTERN_RADIUS, -top, -top + BASE_HEIGHT, BASE_MASS, metal),
            ("glass", GLASS_RADIUS, -top + BASE_HEIGHT, top - CAP_HEIGHT, GLASS_MASS, glass),
            ("cap", LANTERN_RADIUS, top - CAP_HEIGHT, top, CAP_MASS, metal),
        ):
            lantern.add_geom(
                name=f"lantern/{part}",
                type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                size=[radius, (z1 - z0) / 2, 0.0],
                pos=[0.0, 0.0, (z0 + z1) / 2],
                **geom_kwargs(rgba, mass=mass),
            )
        bar_z = top + HANDLE_CLEARANCE + HANDLE_RADIUS
        x = HANDLE_HALF_SPAN
        for part, a, b in (
            ("left", (-x, 0.0, top), (-x, 0.0, bar_z)),
            ("right", (x, 0.0, top), (x, 0.0, bar_z)),
            ("top", (-x, 0.0, bar_z), (x, 0.0, bar_z)),
        ):
            lantern.add_geom(
                name=f"{HANDLE_PREFIX}_{part}",
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                fromto=[*a, *b],
                size=[HANDLE_RADIUS, 0.0, 0.0],
                **geom_kwargs((0.25, 0.25, 0.27, 1), mass=HANDLE_MASS / 3),
            )
        add_fixture_box(scene, "box", BOX_HALF, rgba=(0.72, 0.55, 0.36, 1))

    def bind(self, model: mujoco.MjModel) -> None:
        super().bind(model)
        ids = self.objects["lantern"].geom_ids
        is_handle = np.array([model.geom(int(g)).name.startswith(HANDLE_PREFIX) for g in ids])
        self.handle_geoms, self.body_geoms = ids[is_handle], ids[~is_handle]

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        lantern_xy, box_xy = self.workspace.sample_layout(
            rng, [LANTERN_RADIUS, float(np.hypot(*BOX_HALF[:2]))], gap=0.03
        )
        self.objects["lantern"].set_pose(
            data,
            (*lantern_xy, TABLE_TOP_Z + LANTERN_HALF_HEIGHT),
            yaw_quat(rng.uniform(-np.pi / 2, np.pi / 2)),
        )
        self.fixtures["box"].place(data, box_xy, rng.uniform(-np.pi / 4, np.pi / 4))

    def reset_latches(self) -> None:
        self.lifted_by_handle = False
        self.rest = RestTimer()

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        lantern = self.objects["lantern"]
        pos = lantern.pos(data)
        lifted = bool(pos[2] >= TABLE_TOP_Z + LANTERN_HALF_HEIGHT + LIFT_HEIGHT)
        if lifted and not self.lifted_by_handle:
            self.lifted_by_handle = in_contact(
                model, data, self.handle_geoms, self.robot_geoms
            ) and not in_contact(model, data, self.body_geoms, self.robot_geoms)
        at_rest = self.still(data, "lantern", self.rest)
        upright = up_axis_tilt(lantern.R_world_body(data)) < MAX_TILT
        box = self.fixtures["box"]
        over_box = inside_rectangle(pos, box.pos(data), BOX_HALF[:2], box.yaw(data))
        on_box = in_contact(model, data, lantern.geom_ids, box.geom_ids)
        released = not self.touched_by_robot(model, data, "lantern")
        success = self.lifted_by_handle and upright and over_box and on_box and released and at_rest
        return TaskStatus(
            success=success,
            details={
                "lifted_by_handle": self.lifted_by_handle,
                "upright": upright,
                "over_box": over_box,
                "on_box": on_box,
                "released": released,
                "at_rest": at_rest,
            },
        )
