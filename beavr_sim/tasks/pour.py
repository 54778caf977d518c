"""Pour: grasp a paper cup and tilt it to pour its contents into another cup.

Objects: a paper cup (the source, a free object) 6 cm across, 8 cm tall, 10 g, holding
N_PARTICLES = 8 water drops (free spheres 1.6 cm across, 2 g each: water's density) that stand
in for the liquid; a larger cup (the target, a fixture: another cup standing on the table)
9 cm across and 10 cm tall. Both cups are 16-sided, with 3 mm walls and bottoms (thicker than
paper, so that drops cannot tunnel through); their origins are the centres of their bases.
Reset: cup centres uniform in the workspace, footprints (bounding circles) at least 3 cm apart;
the drops stand in two layers of 2 x 2, 2 mm apart, on the source cup's bottom. With two arms
the target cup's centre lies in the middle band (TabletopTask.SHARED_TARGET_HALF_BAND, 8 cm),
where either hand can pour into it, and the source cup anywhere around it.

The drops are not among ``object_names``: a spilled drop is simply not poured, not a fallen
object that fails the episode (the source cup is).

Success: at least MIN_POURED = ceil(N_PARTICLES / 2) drops are in the target cup and not held
by the source cup. A drop is in a cup when its centre, in that cup's frame, lies within the
cup's inner radius of its axis and between its base (z = 0) and its rim (z = cup height); it
is held by the source cup when it is in it and the source cup opens upwards (its +z axis within
90 degrees of world +z). The "not held" clause stops a source cup set down, drops and all,
inside the target from counting; drops under an upturned source cup do count.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from beavr_sim.robots import Embodiment
from beavr_sim.tasks.base import TaskStatus
from beavr_sim.tasks.objects import (
    FreeObject,
    add_free_body,
    add_mocap_body,
    geom_kwargs,
)
from beavr_sim.tasks.shapes import add_cup, circumradius
from beavr_sim.tasks.tabletop import TabletopTask
from beavr_sim.workcell import TABLE_TOP_Z

CUP_SEGMENTS = 16
CUP_WALL = 0.003
SOURCE_OUTER_RADIUS = 0.03
SOURCE_INNER_RADIUS = SOURCE_OUTER_RADIUS - CUP_WALL
SOURCE_HEIGHT = 0.08
SOURCE_MASS = 0.01
TARGET_OUTER_RADIUS = 0.045
TARGET_INNER_RADIUS = TARGET_OUTER_RADIUS - CUP_WALL
TARGET_HEIGHT = 0.10
N_PARTICLES = 8
PARTICLE_RADIUS = 0.008
PARTICLE_MASS = 0.002
#: Drops start in a PARTICLE_GRID x PARTICLE_GRID grid per layer, PARTICLE_GAP apart.
PARTICLE_GRID = 2
PARTICLE_GAP = 0.002
MIN_POURED = math.ceil(N_PARTICLES / 2)


def particle_name(i: int) -> str:
    return f"particle{i}"


def inside_cup(
    p_world: np.ndarray,
    cup_pos: np.ndarray,
    R_world_cup: np.ndarray,
    inner_radius: float,
    height: float,
) -> np.ndarray:
    """Whether points (``(..., 3)``, world frame) lie in a cup's inner volume (see the module
    docstring): a bool array of the leading shape (a numpy bool for one point)."""
    p_cup = (np.asarray(p_world) - cup_pos) @ R_world_cup  # rows: R_world_cup.T @ (p - pos)
    radial = np.hypot(p_cup[..., 0], p_cup[..., 1])
    return (radial < inner_radius) & (p_cup[..., 2] >= 0.0) & (p_cup[..., 2] <= height)


def particle_offsets() -> np.ndarray:
    """Reset positions of the drops in the source cup's frame (N_PARTICLES x 3)."""
    pitch = 2 * PARTICLE_RADIUS + PARTICLE_GAP
    per_layer = PARTICLE_GRID**2
    offsets = []
    for i in range(N_PARTICLES):
        layer, cell = divmod(i, per_layer)
        row, col = divmod(cell, PARTICLE_GRID)
        offsets.append(
            (
                (col - (PARTICLE_GRID - 1) / 2) * pitch,
                (row - (PARTICLE_GRID - 1) / 2) * pitch,
                CUP_WALL + PARTICLE_GAP / 2 + PARTICLE_RADIUS + layer * pitch,
            )
        )
    return np.array(offsets)


class Pour(TabletopTask):
    name = "Pour"
    instruction = "Grasp the paper cup and tilt it to pour its contents into the other cup."
    max_episode_seconds = 25.0
    embodiments = ("xarm7_leap_right", "xarm7_leap_bimanual", "rx1")
    object_names = ("source_cup",)
    fixture_names = ("target_cup",)

    def __init__(self, embodiment: Embodiment):
        super().__init__(embodiment)
        self.particles: list[FreeObject] = []

    def build_objects(self, scene: mujoco.MjSpec) -> None:
        source = add_free_body(scene, "source_cup")
        add_cup(
            source,
            "source_cup",
            SOURCE_INNER_RADIUS,
            SOURCE_OUTER_RADIUS,
            SOURCE_HEIGHT,
            CUP_WALL,
            CUP_SEGMENTS,
            rgba=(0.95, 0.95, 0.92, 1),
            mass=SOURCE_MASS,
        )
        target = add_mocap_body(scene, "target_cup")
        add_cup(
            target,
            "target_cup",
            TARGET_INNER_RADIUS,
            TARGET_OUTER_RADIUS,
            TARGET_HEIGHT,
            CUP_WALL,
            CUP_SEGMENTS,
            rgba=(0.85, 0.3, 0.25, 1),
        )
        for i in range(N_PARTICLES):
            drop = add_free_body(scene, particle_name(i))
            drop.add_geom(
                name=f"{particle_name(i)}/geom",
                type=mujoco.mjtGeom.mjGEOM_SPHERE,
                size=[PARTICLE_RADIUS, 0.0, 0.0],
                mass=PARTICLE_MASS,
                **geom_kwargs((0.2, 0.45, 0.95, 1)),
            )

    def bind(self, model: mujoco.MjModel) -> None:
        super().bind(model)
        self.particles = [FreeObject.bind(model, particle_name(i)) for i in range(N_PARTICLES)]
        # qpos addresses of every drop's position, one gather per check.
        self._particle_qpos = np.array(
            [[p.qpos_adr + k for k in range(3)] for p in self.particles], dtype=np.intp
        )

    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        (source_xy,), target_xy = self.layout_with_target(
            rng,
            [circumradius(SOURCE_OUTER_RADIUS, CUP_SEGMENTS)],
            circumradius(TARGET_OUTER_RADIUS, CUP_SEGMENTS),
            gap=0.03,
        )
        source_pos = np.array([*source_xy, TABLE_TOP_Z])
        self.objects["source_cup"].set_pose(data, source_pos)
        self.fixtures["target_cup"].place(data, target_xy)
        for particle, offset in zip(self.particles, particle_offsets(), strict=True):
            particle.set_pose(data, source_pos + offset)

    def held_by_source(self, data: mujoco.MjData, p_world: np.ndarray) -> np.ndarray:
        """Whether points (``(..., 3)``) are in the source cup and it opens upwards."""
        source = self.objects["source_cup"]
        R_world_source = source.R_world_body(data)
        inside = inside_cup(
            p_world, source.pos(data), R_world_source, SOURCE_INNER_RADIUS, SOURCE_HEIGHT
        )
        return inside & bool(R_world_source[2, 2] > 0.0)

    def in_target(self, data: mujoco.MjData, p_world: np.ndarray) -> np.ndarray:
        """Whether points (``(..., 3)``) are in the target cup."""
        target = self.fixtures["target_cup"]
        R_world_target = np.zeros(9)
        mujoco.mju_quat2Mat(R_world_target, data.mocap_quat[target.mocap_id])
        return inside_cup(
            p_world,
            target.pos(data),
            R_world_target.reshape(3, 3),
            TARGET_INNER_RADIUS,
            TARGET_HEIGHT,
        )

    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        drops = data.qpos[self._particle_qpos]  # N_PARTICLES x 3, world frame
        held = self.held_by_source(data, drops)
        poured = self.in_target(data, drops) & ~held
        return TaskStatus(
            success=int(poured.sum()) >= MIN_POURED,
            details={"poured": int(poured.sum()), "held_by_source": int(held.sum())},
        )
