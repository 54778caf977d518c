"""Scene objects for tasks: free objects, fixtures and target areas, added to an ``MjSpec``.

Three kinds, each with a builder (before compilation) and a bound handle (after):

- a *free object* (tape roll, cup, block ...) is a body with a free joint; it moves only through
  contact with the robot, the table and other objects: nothing is ever welded or attached;
- a *fixture* (the box that tape and lantern go onto) is a static collision body that a reset
  can move: it is a mocap body, so its pose lives in ``data.mocap_pos``/``data.mocap_quat``;
- a *target area* is a visual-only patch on the table (cameras see it, nothing collides with
  it), also a mocap body so each reset can place it.

Contact parameters are shared so that what the LEAP hand can hold is decided in one place.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.workcell import TABLE_TOP_Z

#: Sliding, torsional, rolling friction of every object (cardboard/paper/plastic on rubber tips).
OBJECT_FRICTION = (1.0, 0.01, 0.0005)
#: Contact dimensionality for objects: 4 adds torsional friction, which keeps a pinched object
#: from spinning about the pinch axis.
OBJECT_CONDIM = 4
#: Contact softness of objects: time constant 5 ms (>= 2 physics steps), critically damped.
OBJECT_SOLREF = (0.005, 1.0)
#: Height of a target-area patch above the table top (thin, visual only).
AREA_THICKNESS = 0.001


def geom_kwargs(rgba, **overrides) -> dict:
    """Keyword arguments for an object's collision geom with the shared contact parameters."""
    kwargs = dict(
        rgba=list(rgba),
        friction=list(OBJECT_FRICTION),
        condim=OBJECT_CONDIM,
        solref=list(OBJECT_SOLREF),
    )
    kwargs.update(overrides)
    return kwargs


def add_free_body(scene: mujoco.MjSpec, name: str) -> mujoco.MjsBody:
    """A body with a free joint named ``name`` (its geoms are added by the caller)."""
    body = scene.worldbody.add_body(name=name, pos=[0.4, 0.0, TABLE_TOP_Z + 0.1])
    body.add_freejoint(name=f"{name}/free")
    return body


def add_box_object(scene: mujoco.MjSpec, name: str, half_size, mass: float, rgba) -> mujoco.MjsBody:
    """A free box of ``half_size`` (metres) and ``mass`` (kg)."""
    body = add_free_body(scene, name)
    body.add_geom(
        name=f"{name}/geom",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=list(half_size),
        mass=mass,
        **geom_kwargs(rgba),
    )
    return body


def add_mocap_body(scene: mujoco.MjSpec, name: str) -> mujoco.MjsBody:
    return scene.worldbody.add_body(name=name, mocap=True, pos=[0.4, 0.0, TABLE_TOP_Z])


def add_fixture_box(scene: mujoco.MjSpec, name: str, half_size, rgba) -> mujoco.MjsBody:
    """A static box standing on the table; its body origin is the centre of its base."""
    body = add_mocap_body(scene, name)
    body.add_geom(
        name=f"{name}/geom",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=list(half_size),
        pos=[0, 0, half_size[2]],
        **geom_kwargs(rgba),
    )
    return body


def add_target_area(scene: mujoco.MjSpec, name: str, half_xy, rgba) -> mujoco.MjsBody:
    """A visual-only rectangular patch on the table: x, y half sizes ``half_xy``."""
    body = add_mocap_body(scene, name)
    body.add_geom(
        name=f"{name}/patch",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[half_xy[0], half_xy[1], AREA_THICKNESS / 2],
        pos=[0, 0, AREA_THICKNESS / 2],
        rgba=list(rgba),
        contype=0,
        conaffinity=0,
    )
    return body


def body_geom_ids(model: mujoco.MjModel, body_id: int) -> np.ndarray:
    return np.flatnonzero(model.geom_bodyid == body_id)


@dataclass(frozen=True)
class FreeObject:
    """A free object bound to a compiled model: its pose, velocity and geoms."""

    name: str
    body_id: int
    qpos_adr: int
    qvel_adr: int
    geom_ids: np.ndarray

    @classmethod
    def bind(cls, model: mujoco.MjModel, name: str) -> FreeObject:
        body = model.body(name)
        joint = model.joint(f"{name}/free")
        return cls(
            name=name,
            body_id=int(body.id),
            qpos_adr=int(joint.qposadr[0]),
            qvel_adr=int(joint.dofadr[0]),
            geom_ids=body_geom_ids(model, body.id),
        )

    def pos(self, data: mujoco.MjData) -> np.ndarray:
        """World position of the body origin (from ``qpos``: valid before ``mj_forward``)."""
        return data.qpos[self.qpos_adr : self.qpos_adr + 3].copy()

    def quat(self, data: mujoco.MjData) -> np.ndarray:
        q = data.qpos[self.qpos_adr + 3 : self.qpos_adr + 7]
        return q / np.linalg.norm(q)

    def R_world_body(self, data: mujoco.MjData) -> np.ndarray:
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, self.quat(data))
        return mat.reshape(3, 3)

    def linear_speed(self, data: mujoco.MjData) -> float:
        return float(np.linalg.norm(data.qvel[self.qvel_adr : self.qvel_adr + 3]))

    def angular_speed(self, data: mujoco.MjData) -> float:
        return float(np.linalg.norm(data.qvel[self.qvel_adr + 3 : self.qvel_adr + 6]))

    def set_pose(self, data: mujoco.MjData, pos, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
        """Place the object with zero velocity."""
        data.qpos[self.qpos_adr : self.qpos_adr + 3] = pos
        data.qpos[self.qpos_adr + 3 : self.qpos_adr + 7] = np.asarray(quat) / np.linalg.norm(quat)
        data.qvel[self.qvel_adr : self.qvel_adr + 6] = 0.0


@dataclass(frozen=True)
class MocapThing:
    """A fixture or target area bound to a compiled model (a mocap body)."""

    name: str
    body_id: int
    mocap_id: int
    geom_ids: np.ndarray

    @classmethod
    def bind(cls, model: mujoco.MjModel, name: str) -> MocapThing:
        body = model.body(name)
        return cls(
            name=name,
            body_id=int(body.id),
            mocap_id=int(model.body_mocapid[body.id]),
            geom_ids=body_geom_ids(model, body.id),
        )

    def pos(self, data: mujoco.MjData) -> np.ndarray:
        return data.mocap_pos[self.mocap_id].copy()

    def yaw(self, data: mujoco.MjData) -> float:
        w, _, _, z = data.mocap_quat[self.mocap_id]
        return float(2 * np.arctan2(z, w))

    def place(self, data: mujoco.MjData, xy, yaw: float = 0.0) -> None:
        """Stand it on the table at ``xy`` turned ``yaw`` radians about +z."""
        data.mocap_pos[self.mocap_id] = (xy[0], xy[1], TABLE_TOP_Z)
        data.mocap_quat[self.mocap_id] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(R, dtype=float).flatten())
    return quat


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
