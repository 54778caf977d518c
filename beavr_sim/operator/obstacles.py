"""The task's fixtures as obstacles for the operator's arm IK.

A fixture (the box that tape and lantern go onto, pour's target cup) is a mocap body of the
env's model: it never moves during an episode, and each reset may place it anew. The operator's
IK runs on a robot-only copy of the scene (it knows no task), so it learns the fixtures from
the env at each reset: :func:`fixture_obstacles` reads them (shapes and poses) from the env's
model and data; :func:`add_obstacles` adds them to an IK spec as mocap bodies and
:func:`place_obstacles` moves those to the fixtures' poses. A new episode of the same task only
moves them; a new task (other shapes) needs the IK model built again.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

#: Geom types an obstacle keeps as they are; other shapes (meshes) become the box that bounds
#: them, which contains them (conservative: the IK keeps a little further away).
PRIMITIVES = frozenset(
    int(t)
    for t in (
        mujoco.mjtGeom.mjGEOM_SPHERE,
        mujoco.mjtGeom.mjGEOM_CAPSULE,
        mujoco.mjtGeom.mjGEOM_ELLIPSOID,
        mujoco.mjtGeom.mjGEOM_CYLINDER,
        mujoco.mjtGeom.mjGEOM_BOX,
    )
)
#: Name prefix of the obstacle bodies in an IK model.
PREFIX = "obstacle/"


def _finite(values, n: int, what: str) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise ValueError(f"{what} needs {n} finite numbers, got {values!r}")
    return out


def _set_pose(obj) -> None:
    """Validate and store a frozen dataclass's ``pos`` (3 finite) and ``quat`` (4 finite,
    non-zero) as tuples of floats."""
    object.__setattr__(obj, "pos", _finite(obj.pos, 3, "pos"))
    quat = _finite(obj.quat, 4, "quat")
    if not np.linalg.norm(quat) > 0:
        raise ValueError(f"quat must be non-zero, got {obj.quat!r}")
    object.__setattr__(obj, "quat", quat)


@dataclass(frozen=True)
class ObstacleGeom:
    """One collision shape of an obstacle: a MuJoCo primitive (``type``, ``size`` as MuJoCo
    reads it) at ``pos`` / ``quat`` (w, x, y, z) in the obstacle's frame."""

    type: int
    size: tuple[float, float, float]
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if int(self.type) not in PRIMITIVES:
            raise ValueError(f"obstacle geom type must be a primitive, got {self.type!r}")
        object.__setattr__(self, "type", int(self.type))
        size = _finite(self.size, 3, "size")
        if min(size) < 0:
            raise ValueError(f"size must be >= 0, got {self.size!r}")
        object.__setattr__(self, "size", size)
        _set_pose(self)


@dataclass(frozen=True)
class Obstacle:
    """A rigid static obstacle: its shapes, and its frame's world pose (position, quaternion
    w, x, y, z)."""

    name: str
    geoms: tuple[ObstacleGeom, ...]
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("an obstacle needs a name")
        geoms = tuple(self.geoms)
        if not geoms or not all(isinstance(g, ObstacleGeom) for g in geoms):
            raise ValueError(f"obstacle {self.name!r} needs ObstacleGeoms, got {self.geoms!r}")
        object.__setattr__(self, "geoms", geoms)
        _set_pose(self)

    @property
    def shape(self) -> tuple:
        """What a model must be built for (name and geoms); the pose is set on data."""
        return (self.name, self.geoms)


def _pose_in(model: mujoco.MjModel, body: int, root: int) -> tuple[np.ndarray, np.ndarray]:
    """Pose of ``body`` in the frame of ``root``, an ancestor it is welded to."""
    pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    while body != root:
        p, q = np.zeros(3), np.zeros(4)
        mujoco.mju_mulPose(p, q, model.body_pos[body], model.body_quat[body], pos, quat)
        pos, quat, body = p, q, int(model.body_parentid[body])
    return pos, quat


def _geom_of(model: mujoco.MjModel, g: int, body_pos, body_quat) -> ObstacleGeom | None:
    """Geom ``g`` in its obstacle's frame (its body at ``body_pos``, ``body_quat`` there)."""
    pos, quat = np.zeros(3), np.zeros(4)
    mujoco.mju_mulPose(pos, quat, body_pos, body_quat, model.geom_pos[g], model.geom_quat[g])
    kind = int(model.geom_type[g])
    if kind in PRIMITIVES:
        return ObstacleGeom(kind, tuple(model.geom_size[g]), tuple(pos), tuple(quat))
    if kind == mujoco.mjtGeom.mjGEOM_PLANE or not np.isfinite(model.geom_aabb[g]).all():
        return None  # unbounded: no box contains it
    centre, half = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
    offset = np.zeros(3)
    mujoco.mju_rotVecQuat(offset, centre, quat)
    box = int(mujoco.mjtGeom.mjGEOM_BOX)
    return ObstacleGeom(box, tuple(half), tuple(pos + offset), tuple(quat))


def fixture_obstacles(model: mujoco.MjModel, data: mujoco.MjData) -> tuple[Obstacle, ...]:
    """The fixtures of an env (its model and data after reset) as obstacles: one per mocap
    body with colliding geoms (its own and those of bodies welded to it), at the pose the reset
    gave it. Visual-only geoms (target areas) are left out."""
    obstacles = []
    for b in range(model.nbody):
        mocap = int(model.body_mocapid[b])
        if mocap < 0:
            continue
        geoms = []
        welded = model.body_weldid[model.geom_bodyid] == b
        colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)  # not visual
        for g in np.flatnonzero(welded & colliding):
            body = int(model.geom_bodyid[g])
            geom = _geom_of(model, int(g), *_pose_in(model, body, b))
            if geom is not None:
                geoms.append(geom)
        if geoms:
            obstacles.append(
                Obstacle(
                    model.body(b).name or f"mocap{mocap}",
                    tuple(geoms),
                    tuple(data.mocap_pos[mocap]),
                    tuple(data.mocap_quat[mocap]),
                )
            )
    return tuple(obstacles)


def add_obstacles(spec: mujoco.MjSpec, obstacles: Sequence[Obstacle]) -> None:
    """Add ``obstacles`` to ``spec`` as mocap bodies ``obstacle/<name>`` (after everything
    else, so the ids of the bodies and geoms already there do not change), colliding, visible
    in no default group."""
    for o in obstacles:
        body = spec.worldbody.add_body(name=PREFIX + o.name, mocap=True, pos=list(o.pos))
        body.quat = list(o.quat)
        for i, g in enumerate(o.geoms):
            body.add_geom(
                name=f"{PREFIX}{o.name}/geom{i}",
                type=mujoco.mjtGeom(g.type),
                size=list(g.size),
                pos=list(g.pos),
                quat=list(g.quat),
                contype=1,
                conaffinity=1,
                group=5,
            )


def obstacle_geoms(model: mujoco.MjModel, obstacles: Sequence[Obstacle]) -> list[int]:
    """The geom ids of ``obstacles`` in a model built with :func:`add_obstacles`."""
    return [
        model.geom(f"{PREFIX}{o.name}/geom{i}").id for o in obstacles for i in range(len(o.geoms))
    ]


def place_obstacles(
    model: mujoco.MjModel, data: mujoco.MjData, obstacles: Sequence[Obstacle]
) -> None:
    """Move the obstacle bodies of ``data`` (a model built with :func:`add_obstacles` for the
    same shapes) to the obstacles' poses (kinematics not updated)."""
    for o in obstacles:
        mocap = int(model.body_mocapid[model.body(PREFIX + o.name).id])
        data.mocap_pos[mocap] = o.pos
        data.mocap_quat[mocap] = np.asarray(o.quat) / np.linalg.norm(o.quat)
