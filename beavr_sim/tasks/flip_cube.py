"""FlipCube: turn a cube so that another of its faces points up.

Objects: a foam cube, 6 cm, 60 g, each face a different colour (visual plates, so cameras
and people can see which face is up). Reset: cube centre uniform in the workspace, a random
one of its six faces up, yaw uniform in +-45 degrees.

Success: the face pointing up (checks.face_up) differs from the face that pointed up at the
start of the episode (the ``start_face`` latch, taken at the first evaluation), the cube
stands on the table (touching it, its up face within 15 degrees of vertical), the robot no
longer touches it and it has been at rest (checks.REST_*). Lifted and put back on the same
face is not a success.
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.checks import RestTimer, face_up, in_contact
from beavr_sim.tasks.objects import add_box_object, mat_to_quat
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

CUBE_HALF = 0.03
CUBE_MASS = 0.06
MAX_TILT = np.deg2rad(15.0)
#: Face colours (RGBA): +x red, -x cyan, +y green, -y magenta, +z blue, -z yellow.
FACE_COLOURS = {
    "+x": (0.85, 0.2, 0.2, 1),
    "-x": (0.2, 0.8, 0.85, 1),
    "+y": (0.25, 0.75, 0.3, 1),
    "-y": (0.8, 0.3, 0.8, 1),
    "+z": (0.2, 0.35, 0.85, 1),
    "-z": (0.9, 0.85, 0.2, 1),
}
#: Body rotations that put each face up (columns: body axes in the world).
_FACE_UP_ROTATIONS = {
    "+z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "+x": np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], float),
    "-x": np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float),
    "+y": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float),
    "-y": np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float),
}


class FlipCube(TabletopTask):
    name = "FlipCube"
    instruction = "Flip the cube onto another of its faces."
    max_episode_seconds = 20.0
    embodiments = ("xarm7_leap_right",)
    object_names = ("cube",)

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        body = add_box_object(scene, "cube", (CUBE_HALF,) * 3, CUBE_MASS, (0.9, 0.9, 0.9, 1))
        for face, rgba in FACE_COLOURS.items():
            axis = "xyz".index(face[1])
            sign = 1.0 if face[0] == "+" else -1.0
            pos, size = np.zeros(3), np.full(3, CUBE_HALF * 0.85)
            pos[axis], size[axis] = sign * CUBE_HALF, 0.0005
            body.add_geom(
                name=f"cube/face{face}",
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=list(size),
                pos=list(pos),
                rgba=list(rgba),
                contype=0,
                conaffinity=0,
                mass=0,
            )

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        (xy,) = self.workspace.sample_layout(rng, [CUBE_HALF * np.sqrt(2)])
        face = list(_FACE_UP_ROTATIONS)[rng.integers(6)]
        yaw = rng.uniform(-np.pi / 4, np.pi / 4)
        c, s = np.cos(yaw), np.sin(yaw)
        R_world_body = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ _FACE_UP_ROTATIONS[face]
        self.objects["cube"].set_pose(
            data, (*xy, TABLE_TOP_Z + CUBE_HALF), mat_to_quat(R_world_body)
        )

    def reset_latches(self) -> None:
        self.start_face: str | None = None
        self.rest = RestTimer()

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        cube = self.objects["cube"]
        R_world_cube = cube.R_world_body(data)
        face = face_up(R_world_cube)
        if self.start_face is None:
            self.start_face = face
        flipped = face != self.start_face
        level = bool(np.max(np.abs(R_world_cube[2, :])) > np.cos(MAX_TILT))
        on_table = in_contact(model, data, cube.geom_ids, self.table_geoms)
        released = not self.touched_by_robot(model, data, "cube")
        at_rest = self.still(data, "cube", self.rest)
        success = flipped and level and on_table and released and at_rest
        return TaskStatus(
            success=success,
            details={
                "start_face": self.start_face,
                "face_up": face,
                "flipped": flipped,
                "level": level,
                "on_table": on_table,
                "released": released,
                "at_rest": at_rest,
            },
        )
