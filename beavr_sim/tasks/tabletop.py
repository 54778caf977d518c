"""The shared base of the benchmark tasks: objects on the table in front of the robot.

A :class:`TabletopTask` owns its free objects, fixtures and target areas; subclasses say
which objects to build, how a reset lays them out and what success means. The base does the
rest: binding, the workspace each embodiment can reach, and the common failure (an object
fell off the table).
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.robots import Embodiment
from beavr_sim.tasks.base import Task, TaskStatus
from beavr_sim.tasks.checks import RestTimer, in_contact, robot_geom_ids
from beavr_sim.tasks.objects import FreeObject, MocapThing, body_geom_ids
from beavr_sim.workcell import TABLE_HALF_Y, TABLE_TOP_Z, TABLE_X

#: An object whose origin drops this far below the table top has fallen off (failure).
FALLEN_BELOW_TABLE = 0.05


@dataclass(frozen=True)
class Workspace:
    """The rectangle of the table top (world x, y ranges, metres) where resets put objects."""

    x: tuple[float, float]
    y: tuple[float, float]

    @classmethod
    def for_embodiment(cls, embodiment: Embodiment) -> Workspace:
        """The embodiment's own workspace if it names one; else in front of the arm bases:
        0.35-0.55 m ahead, spanning the bases plus 0.15 m.

        For one arm the rectangle leans 5 cm to the hand's thumb-free side (right arm: to
        its right), where the hand reaches comfortably without crossing the base.
        """
        if embodiment.spec.workspace is not None:
            (x0, x1), (y0, y1) = embodiment.spec.workspace
            return cls(x=(x0, x1), y=(y0, y1))
        ys = [e.base_pos[1] for e in embodiment.spec.effectors]
        if len(ys) == 1:
            lean = -0.05 if embodiment.spec.effectors[0].side == "right" else 0.05
            return cls(x=(0.35, 0.55), y=(ys[0] + lean - 0.15, ys[0] + lean + 0.15))
        return cls(x=(0.35, 0.55), y=(min(ys) - 0.05, max(ys) + 0.05))

    def sample_layout(
        self,
        rng: np.random.Generator,
        radii: list[float],
        gap: float = 0.03,
        max_tries: int = 1000,
        avoid: list[tuple[np.ndarray, float]] = (),
    ) -> list[np.ndarray]:
        """One xy per radius, inside the workspace, footprints ``gap`` apart and apart from
        the ``avoid`` footprints (xy, radius) already placed.

        Rejection sampling of whole layouts in the given order first (the layouts every seed
        has always given). Tight layouts rarely succeed that way (a wide target with two
        blocks: 0.6 % of tries, so 1,000 tries failed about once in 600 resets); if
        ``max_tries`` fail, footprints are placed largest first, each retried up to 50 times
        where it is before the layout restarts.
        """
        layout = self._sample_in_order(rng, list(radii), gap, max_tries, avoid)
        if layout is None:
            order = sorted(range(len(radii)), key=lambda i: -radii[i])
            ordered = self._sample_in_order(
                rng, [radii[i] for i in order], gap, max_tries, avoid, tries_each=50
            )
            if ordered is not None:
                layout = [None] * len(radii)
                for i, xy in zip(order, ordered, strict=True):
                    layout[i] = xy
        if layout is None:
            raise RuntimeError(
                f"could not lay out objects of radii {list(radii)} (gap {gap}) in {self}"
            )
        return layout

    def _sample_in_order(
        self, rng, radii, gap, max_tries, avoid, tries_each: int = 1
    ) -> list[np.ndarray] | None:
        for _ in range(max_tries):
            placed = [(np.asarray(xy, float), float(r)) for xy, r in avoid]
            for r in radii:
                for _ in range(tries_each):
                    p = np.array(
                        [
                            rng.uniform(self.x[0] + r, self.x[1] - r),
                            rng.uniform(self.y[0], self.y[1]),
                        ]
                    )
                    if all(np.linalg.norm(p - q) >= r + rq + gap for q, rq in placed):
                        placed.append((p, r))
                        break
                else:
                    break
            if len(placed) == len(avoid) + len(radii):
                return [p for p, _ in placed[len(avoid) :]]
        return None

    def middle(self, half_width: float) -> Workspace:
        """The band of this workspace within ``half_width`` of its centre line (in y)."""
        centre = (self.y[0] + self.y[1]) / 2
        return Workspace(x=self.x, y=(centre - half_width, centre + half_width))


#: Components of one pose in :meth:`TabletopTask.state`.
POSE_COMPONENTS = ("x", "y", "z", "qw", "qx", "qy", "qz")


class TabletopTask(Task):
    """Free objects, fixtures and target areas on the table; subclasses add a checker."""

    #: Names of the free objects the subclass builds (bound as ``self.objects[name]``).
    object_names: tuple[str, ...] = ()
    #: Names of fixtures and target areas (mocap bodies, bound as ``self.fixtures[name]``).
    fixture_names: tuple[str, ...] = ()

    def __init__(self, embodiment: Embodiment):
        super().__init__(embodiment)
        self.workspace = Workspace.for_embodiment(embodiment)
        self.objects: dict[str, FreeObject] = {}
        self.fixtures: dict[str, MocapThing] = {}
        self.robot_geoms = np.zeros(0, dtype=int)
        self.table_geoms = np.zeros(0, dtype=int)

    # ----------------------------------------------------------------- Task hooks
    def build(self, scene: mujoco.MjSpec) -> None:
        self.build_objects(scene)

    def bind(self, model: mujoco.MjModel) -> None:
        self.objects = {n: FreeObject.bind(model, n) for n in self.object_names}
        self.fixtures = {n: MocapThing.bind(model, n) for n in self.fixture_names}
        self.robot_geoms = robot_geom_ids(model, [e.name + "/" for e in self.embodiment.effectors])
        self.table_geoms = body_geom_ids(model, model.body("table").id)

    def initialize_episode(
        self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator
    ) -> None:
        self.reset_latches()
        self.place_objects(data, rng)

    @property
    def state_names(self) -> tuple[str, ...]:
        things = (*self.object_names, *self.fixture_names)
        return tuple(f"{n}/{c}" for n in things for c in POSE_COMPONENTS)

    def state(self, data: mujoco.MjData) -> np.ndarray:
        """Pose of every object, then every fixture: position (m) and unit quaternion (w >= 0)."""
        poses = [np.concatenate([o.pos(data), o.quat(data)]) for o in self.objects.values()]
        poses += [
            np.concatenate([data.mocap_pos[f.mocap_id], data.mocap_quat[f.mocap_id]])
            for f in self.fixtures.values()
        ]
        if not poses:
            return np.zeros(0)
        state = np.stack(poses)
        state[state[:, 3] < 0, 3:] *= -1.0
        return state.reshape(-1)

    def evaluate(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        fallen = [n for n, o in self.objects.items() if self.off_table(o.pos(data))]
        status = self.check(model, data)
        if fallen:
            details = {**status.details, "fallen": ",".join(fallen)}
            return TaskStatus(success=False, failure=True, details=details)
        return status

    # ----------------------------------------------------------- subclass hooks
    @abstractmethod
    def build_objects(self, scene: mujoco.MjSpec) -> None:
        """Add the free objects, fixtures and target areas to the scene."""

    @abstractmethod
    def place_objects(self, data: mujoco.MjData, rng: np.random.Generator) -> None:
        """Draw a layout from ``rng`` and put everything in place (zero velocities)."""

    @abstractmethod
    def check(self, model: mujoco.MjModel, data: mujoco.MjData) -> TaskStatus:
        """Success (and task-specific failure) of the current state; update latches."""

    def reset_latches(self) -> None:
        """Clear every latch (called at the start of each episode)."""

    #: With two arms, the target area's centre lies within this of the middle line (y), where
    #: both hands reach it.
    SHARED_TARGET_HALF_BAND = 0.08

    def layout_with_target(
        self, rng: np.random.Generator, object_radii: list[float], target_radius: float, gap: float
    ) -> tuple[list[np.ndarray], np.ndarray]:
        """Object xys and a target-area xy: all uniform in the workspace with one arm; with
        two, the target first, in the middle band, then the objects around it."""
        if len(self.embodiment.effectors) == 1:
            *objects, target = self.workspace.sample_layout(
                rng, [*object_radii, target_radius], gap=gap
            )
            return objects, target
        (target,) = self.workspace.middle(self.SHARED_TARGET_HALF_BAND).sample_layout(
            rng, [target_radius]
        )
        objects = self.workspace.sample_layout(
            rng, object_radii, gap=gap, avoid=[(target, target_radius)]
        )
        return objects, target

    # ------------------------------------------------------------------- helpers
    @staticmethod
    def off_table(pos: np.ndarray) -> bool:
        return bool(
            pos[2] < TABLE_TOP_Z - FALLEN_BELOW_TABLE
            or not (TABLE_X[0] <= pos[0] <= TABLE_X[1])
            or abs(pos[1]) > TABLE_HALF_Y
        )

    def touched_by_robot(self, model: mujoco.MjModel, data: mujoco.MjData, name: str) -> bool:
        return in_contact(model, data, self.objects[name].geom_ids, self.robot_geoms)

    def still(self, data: mujoco.MjData, name: str, timer: RestTimer) -> bool:
        """Feed ``timer`` with object ``name``'s speeds; True once it has been at rest."""
        obj = self.objects[name]
        return timer.update(data.time, obj.linear_speed(data), obj.angular_speed(data))
