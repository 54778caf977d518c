"""Tape: put the ring finger through a roll of tape, lift it, set it down on top of a box.

Objects: a roll of masking tape lying flat, hole 7.6 cm across (a 3-inch core), outside 11 cm
across, 2.5 cm wide (tall as it lies), 100 g, built as a ring of 16 box segments (the hole is
the 16-gon whose inscribed circle is 7.6 cm across); a 14 x 14 x 8 cm cardboard box (a fixture).
Reset: roll and box centres uniform in the workspace, footprints (bounding circles) at least
3 cm apart; roll yaw uniform in one segment's angle, box yaw uniform in +-45 degrees.

Success: the ``lifted_with_finger`` latch is set (at some step the roll's centre was
>= LIFT_HEIGHT above its resting height on the table while the ring fingertip was in the hole:
the fingertip pad site, in the roll's frame, at radius < TAPE_INNER_RADIUS from the roll's axis
and within TAPE_HALF_WIDTH + IN_HOLE_Z_MARGIN of its mid-plane), and now the roll rests on the
box: it touches the box, its centre lies over the box top (x, y inside the box footprint), the
robot does not touch it and it has been at rest (checks.REST_*).
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.checks import RestTimer, in_contact, inside_rectangle
from beavr_sim.tasks.objects import add_fixture_box, add_free_body, yaw_quat
from beavr_sim.tasks.shapes import add_ring, circumradius
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

TAPE_INNER_RADIUS = 0.038
TAPE_OUTER_RADIUS = 0.055
TAPE_HALF_WIDTH = 0.0125
TAPE_MASS = 0.1
TAPE_SEGMENTS = 16
BOX_HALF = (0.07, 0.07, 0.04)
LIFT_HEIGHT = 0.03
#: The fingertip counts as in the hole up to this far above or below the roll's faces.
IN_HOLE_Z_MARGIN = 0.01
#: The fingertip pad site of the LEAP hand's ring finger (the third finger), without prefix.
RING_TIP_SITE = "ring_tip"


class Tape(TabletopTask):
    name = "Tape"
    instruction = (
        "Insert the ring finger into the roll of tape, lift it and set it down on top of the box."
    )
    max_episode_seconds = 30.0
    embodiments = ("xarm7_leap_right",)
    object_names = ("tape",)
    fixture_names = ("box",)

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        tape = add_free_body(scene, "tape")
        add_ring(
            tape,
            "tape/segment",
            TAPE_INNER_RADIUS,
            TAPE_OUTER_RADIUS,
            (-TAPE_HALF_WIDTH, TAPE_HALF_WIDTH),
            TAPE_SEGMENTS,
            rgba=(0.93, 0.86, 0.62, 1),
            mass=TAPE_MASS,
        )
        add_fixture_box(scene, "box", BOX_HALF, rgba=(0.72, 0.55, 0.36, 1))

    def bind(self, model: mujoco.MjModel) -> None:
        super().bind(model)
        effector = self.embodiment.effectors[0]
        self.ring_tip_site = int(model.site(f"{effector.name}/{RING_TIP_SITE}").id)

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        tape_xy, box_xy = self.workspace.sample_layout(
            rng,
            [circumradius(TAPE_OUTER_RADIUS, TAPE_SEGMENTS), float(np.hypot(*BOX_HALF[:2]))],
            gap=0.03,
        )
        tape_yaw = rng.uniform(0.0, 2 * np.pi / TAPE_SEGMENTS)
        self.objects["tape"].set_pose(
            data, (*tape_xy, TABLE_TOP_Z + TAPE_HALF_WIDTH), yaw_quat(tape_yaw)
        )
        self.fixtures["box"].place(data, box_xy, rng.uniform(-np.pi / 4, np.pi / 4))

    def reset_latches(self) -> None:
        self.lifted_with_finger = False
        self.rest = RestTimer()

    def ring_tip_in_hole(self, data: mujoco.MjData) -> bool:
        """Whether the ring fingertip site lies in the roll's hole (see the module docstring).

        Site and roll poses both come from the last kinematics pass, so they are consistent.
        """
        body = self.objects["tape"].body_id
        R_world_tape = data.xmat[body].reshape(3, 3)
        p_tape_tip = R_world_tape.T @ (data.site_xpos[self.ring_tip_site] - data.xpos[body])
        return bool(
            np.hypot(p_tape_tip[0], p_tape_tip[1]) < TAPE_INNER_RADIUS
            and abs(p_tape_tip[2]) < TAPE_HALF_WIDTH + IN_HOLE_Z_MARGIN
        )

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        tape = self.objects["tape"]
        pos = tape.pos(data)
        lifted = bool(pos[2] >= TABLE_TOP_Z + TAPE_HALF_WIDTH + LIFT_HEIGHT)
        self.lifted_with_finger |= lifted and self.ring_tip_in_hole(data)
        at_rest = self.still(data, "tape", self.rest)
        box = self.fixtures["box"]
        over_box = inside_rectangle(pos, box.pos(data), BOX_HALF[:2], box.yaw(data))
        on_box = in_contact(model, data, tape.geom_ids, box.geom_ids)
        released = not self.touched_by_robot(model, data, "tape")
        success = self.lifted_with_finger and over_box and on_box and released and at_rest
        return TaskStatus(
            success=success,
            details={
                "lifted_with_finger": self.lifted_with_finger,
                "over_box": over_box,
                "on_box": on_box,
                "released": released,
                "at_rest": at_rest,
            },
        )
