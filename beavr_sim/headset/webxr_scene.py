"""The twin in the headset: its geometry once, then its live poses, for the WebXR page to draw.

:class:`TwinGeometry` picks the geoms a viewer shows (groups 0-2, not transparent; planes
left out: the headset has its own floor) and describes each as a shape the page draws with
WebGL: box, sphere, capsule, cylinder, ellipsoid, or mesh. A mesh's triangles are sent once,
in the ``scene`` message (:func:`encode_mesh`: vertices quantised to 16 bits over the mesh's
bounding box, faces as 16- or 32-bit indices, base64), shared by every geom that uses it; its
pose and size are its bounding box's, which the page draws where a mesh cannot be read.
:class:`TwinFeed` is a tick listener: at most ``rate_hz`` times a wall second it copies the
poses of the geoms that move (a few hundred numbers, on the control thread) and hands them to
the server, which encodes and sends them on its own thread.

Messages (``docs/formats.md``): ``scene`` (shapes, sizes, colours, every pose, which ones
move) and ``twin`` (the moving geoms' poses, pause and hold state). A pose is 12 numbers in
the world frame (Z up): position, then ``R_world_geom`` row by row.
"""

from __future__ import annotations

import base64
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.headset.webxr_protocol import PROTOCOL_VERSION
from beavr_sim.wire.records import JointCommand, Tick

SHAPES = {
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_MESH): "mesh",
}
VISIBLE_GROUPS = (0, 1, 2)
#: Decimals sent: 0.1 mm, 1e-4 of a rotation matrix entry.
DECIMALS = 4
#: A mesh vertex is sent as three int16 in [-QUANT, QUANT]: its position in the mesh's
#: bounding box, centre 0, faces at +-QUANT (1/65534 of the box: 3 um on a 20 cm link).
QUANT = 32767
#: Meshes of at most this many vertices send their faces as uint16, larger ones as uint32.
U16_VERTICES = 65536
#: MuJoCo's default geom colour: a geom with a material and this colour takes the material's.
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], dtype=np.float32)


def encode_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[bytes, np.ndarray, np.ndarray]:
    """``(data, centre, half)`` of a triangle mesh: ``data`` is the vertices quantised over
    their bounding box (int16 little-endian, x y z per vertex, ``v = centre + half * q /
    QUANT``), zero-padded to a multiple of 4 bytes, then the faces (3 indices each, uint16
    little-endian up to :data:`U16_VERTICES` vertices, uint32 beyond)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces).reshape(-1, 3)
    if len(v) == 0 or len(f) == 0:
        raise ValueError("a mesh needs vertices and faces")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"face indices out of range 0..{len(v) - 1}")
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    q = np.round((v - centre) / np.maximum(half, 1e-12) * QUANT)
    data = np.clip(q, -QUANT, QUANT).astype("<i2").tobytes()
    data += b"\0" * (-len(data) % 4)
    index = "<u2" if len(v) <= U16_VERTICES else "<u4"
    return data + f.astype(index).tobytes(), centre, half


def decode_mesh(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(unit_vertices, faces)`` of a ``meshes`` entry of the scene message (the page's
    decoding, for tests): vertices in [-1, 1] of the bounding box (times the geom's ``sizes``,
    at its pose: the world), faces as vertex indices."""
    n, m = int(entry["vertices"]), int(entry["faces"])
    data = base64.b64decode(entry["data"])
    start = 6 * n + (-6 * n % 4)
    index = "<u2" if n <= U16_VERTICES else "<u4"
    if len(data) != start + 3 * m * np.dtype(index).itemsize:
        raise ValueError(f"mesh {entry.get('name')!r}: {len(data)} bytes do not match its counts")
    q = np.frombuffer(data, dtype="<i2", count=3 * n).reshape(n, 3)
    faces = np.frombuffer(data, dtype=index, offset=start).reshape(m, 3)
    return q.astype(np.float64) / QUANT, faces.astype(np.int64)


def _rgba(model: mujoco.MjModel, g: int) -> np.ndarray:
    """A geom's colour as MuJoCo draws it: its own, or its material's if it has one and its
    own is the default."""
    mat = int(model.geom_matid[g])
    if mat >= 0 and np.array_equal(model.geom_rgba[g], _DEFAULT_RGBA):
        return model.mat_rgba[mat].astype(np.float64)
    return model.geom_rgba[g].astype(np.float64)


@dataclass(frozen=True, eq=False)
class TwinGeometry:
    """The drawn geoms of a model: ``geom_ids`` (model ids), their ``shapes``, ``sizes``
    (the shape's half extents / radius, half length; a mesh's bounding box half extents),
    ``rgba``, ``centres`` (the shape's centre in the geom frame: a mesh's bounding box is off
    its origin), ``dynamic`` (indices into ``geom_ids`` of the geoms that can move),
    ``mesh_index`` (per geom, its entry in ``meshes``, -1 for a primitive) and ``meshes``
    (each distinct mesh once: ``name``, ``vertices``, ``faces``, ``data``: base64 of
    :func:`encode_mesh`)."""

    geom_ids: np.ndarray
    shapes: tuple[str, ...]
    sizes: np.ndarray
    rgba: np.ndarray
    centres: np.ndarray
    dynamic: np.ndarray
    mesh_index: np.ndarray
    #: Per drawn geom: its body, and its shape's centre and rotation in that body's frame.
    #: Poses come from body poses, so a physics model's data (same bodies, no visual geoms)
    #: drives the geometry of the model it was drawn from.
    bodies: np.ndarray
    p_body_shape: np.ndarray
    R_body_shape: np.ndarray
    meshes: tuple[dict, ...] = ()

    @classmethod
    def from_model(cls, model: mujoco.MjModel) -> TwinGeometry:
        ids, shapes, sizes, centres, mesh_index = [], [], [], [], []
        meshes: list[dict] = []
        by_mesh: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}  # model mesh -> entry
        by_data: dict[bytes, int] = {}  # identical meshes (both arms' links) sent once
        for g in range(model.ngeom):
            kind = int(model.geom_type[g])
            if (
                kind not in SHAPES
                or int(model.geom_group[g]) not in VISIBLE_GROUPS
                or model.geom_rgba[g, 3] <= 0.0
            ):
                continue
            ids.append(g)
            shapes.append(SHAPES[kind])
            if kind == mujoco.mjtGeom.mjGEOM_MESH:
                k = int(model.geom_dataid[g])
                if k not in by_mesh:
                    by_mesh[k] = _add_mesh(model, k, meshes, by_data)
                entry, centre, half = by_mesh[k]
                mesh_index.append(entry)
                centres.append(centre)
                sizes.append(half)
            else:
                mesh_index.append(-1)
                centres.append(np.zeros(3))
                sizes.append(model.geom_size[g].copy())
        geom_ids = np.array(ids, dtype=int)
        bodies = model.geom_bodyid[geom_ids]
        moves = (model.body_weldid[bodies] != 0) | (model.body_mocapid[bodies] >= 0)
        R_body_geom = np.zeros((len(geom_ids), 9))
        for row, g in zip(R_body_geom, geom_ids, strict=True):
            mujoco.mju_quat2Mat(row, model.geom_quat[g])
        R_body_geom = R_body_geom.reshape(-1, 3, 3)
        centres_geom = np.array(centres, dtype=np.float64).reshape(-1, 3)
        p_body_shape = model.geom_pos[geom_ids] + np.einsum("nij,nj->ni", R_body_geom, centres_geom)
        return cls(
            geom_ids=geom_ids,
            shapes=tuple(shapes),
            sizes=np.array(sizes, dtype=np.float64).reshape(-1, 3),
            rgba=np.array([_rgba(model, g) for g in geom_ids], dtype=np.float64).reshape(-1, 4),
            centres=np.array(centres, dtype=np.float64).reshape(-1, 3),
            dynamic=np.flatnonzero(moves),
            mesh_index=np.array(mesh_index, dtype=int),
            bodies=np.asarray(bodies, dtype=int),
            p_body_shape=p_body_shape.reshape(-1, 3),
            R_body_shape=R_body_geom,
            meshes=tuple(meshes),
        )

    def poses(self, data: mujoco.MjData, which: np.ndarray | None = None) -> np.ndarray:
        """(n, 12) world poses of the drawn geoms (``which``: indices into ``geom_ids``)."""
        index = np.arange(len(self.geom_ids)) if which is None else which
        bodies = self.bodies[index]
        R_world_body = data.xmat[bodies].reshape(-1, 3, 3)
        p = data.xpos[bodies] + np.einsum("nij,nj->ni", R_world_body, self.p_body_shape[index])
        R = R_world_body @ self.R_body_shape[index]
        return np.concatenate([p, R.reshape(-1, 9)], axis=1)

    def scene_message(self, data: mujoco.MjData, **info: object) -> dict:
        return {
            "v": PROTOCOL_VERSION,
            "type": "scene",
            **info,
            "shapes": list(self.shapes),
            "sizes": np.round(self.sizes, DECIMALS).ravel(),
            "rgba": np.round(self.rgba, 3).ravel(),
            "pose": np.round(self.poses(data), DECIMALS).ravel(),
            "dynamic": self.dynamic,
            "mesh": self.mesh_index,
            "meshes": list(self.meshes),
        }

    def moving_poses(self, data: mujoco.MjData) -> np.ndarray:
        """The ``twin`` message's ``pose``: the moving geoms' poses, rounded, flat."""
        return np.round(self.poses(data, self.dynamic), DECIMALS).ravel()

    def twin_message(self, data: mujoco.MjData, t: float, **status: object) -> dict:
        return twin_message(t, self.moving_poses(data), **status)


def twin_message(t: float, pose: np.ndarray | list[float], **status: object) -> dict:
    """The ``twin`` message: the moving geoms' poses (:meth:`TwinGeometry.moving_poses`) at
    twin time ``t``, with ``status`` (:func:`page_status`)."""
    return {"v": PROTOCOL_VERSION, "type": "twin", "t": round(float(t), 4), "pose": pose, **status}


def page_status(commands: Mapping[str, JointCommand], paused: bool) -> dict:
    """The ``twin`` message's status: whether the operator holds paused and why each
    effector of ``commands`` (the newest per effector) holds."""
    holds = {name: cmd.reason or "hold" for name, cmd in commands.items() if cmd.hold}
    return {"paused": bool(paused), "holds": holds}


class RateGate:
    """At most ``rate_hz`` openings per second of ``clock``: :meth:`due` is true once per
    period (a late call moves the next opening on; no catch-up)."""

    def __init__(self, rate_hz: float, clock: Callable[[], float] = time.monotonic):
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
        self.period_s = 1.0 / rate_hz
        self.clock = clock
        self._next = -math.inf

    def due(self) -> bool:
        now = self.clock()
        if now < self._next:
            return False
        self._next = now + self.period_s
        return True


def _add_mesh(
    model: mujoco.MjModel, k: int, meshes: list[dict], by_data: dict[bytes, int]
) -> tuple[int, np.ndarray, np.ndarray]:
    """Model mesh ``k`` as an entry of ``meshes`` (a new one unless the same data is there):
    ``(entry index, centre, half extents)`` of its bounding box in the geom frame."""
    v0, nv = int(model.mesh_vertadr[k]), int(model.mesh_vertnum[k])
    f0, nf = int(model.mesh_faceadr[k]), int(model.mesh_facenum[k])
    data, centre, half = encode_mesh(model.mesh_vert[v0 : v0 + nv], model.mesh_face[f0 : f0 + nf])
    if data not in by_data:
        by_data[data] = len(meshes)
        meshes.append(
            {
                "name": mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_MESH, k) or f"mesh{k}",
                "vertices": nv,
                "faces": nf,
                "data": base64.b64encode(data).decode("ascii"),
            }
        )
    return by_data[data], centre, half


class TwinFeed:
    """A tick listener sending the twin's poses to the page at most ``rate_hz`` per wall
    second, with the pause state and why each effector holds (``operator``: the loop's
    :class:`~beavr_sim.operator.operator.Operator`, read only)."""

    def __init__(
        self,
        server,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        rate_hz: float = 15.0,
        operator=None,
        info: dict | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.gate = RateGate(rate_hz, clock)
        self.server = server
        self.data = data
        self.operator = operator
        self.geometry = TwinGeometry.from_model(model)
        server.publish("scene", self.geometry.scene_message(data, **(info or {})))

    def __call__(self, tick: Tick) -> None:
        if not self.gate.due():
            return
        paused = bool(self.operator.paused) if self.operator is not None else False
        status = page_status(tick.commands, paused)
        self.server.publish("twin", self.geometry.twin_message(self.data, tick.state.t, **status))
