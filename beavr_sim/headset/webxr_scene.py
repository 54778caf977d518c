"""The twin in the headset: its geometry once, then its live poses, for the WebXR page to draw.

:class:`TwinGeometry` picks the geoms a viewer shows (groups 0-2, not transparent; planes
left out: the headset has its own floor) and describes each as a simple shape the page draws
with WebGL (box, sphere, capsule, cylinder, ellipsoid; a mesh as its bounding box).
:class:`TwinFeed` is a tick listener: at most ``rate_hz`` times a wall second it copies the
poses of the geoms that move (a few hundred numbers, on the control thread) and hands them to
the server, which encodes and sends them on its own thread.

Messages (``docs/formats.md``): ``scene`` (shapes, sizes, colours, every pose, which ones
move) and ``twin`` (the moving geoms' poses, pause and hold state). A pose is 12 numbers in
the world frame (Z up): position, then ``R_world_geom`` row by row.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.headset.webxr_protocol import PROTOCOL_VERSION
from beavr_sim.wire.records import Tick

SHAPES = {
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
    int(mujoco.mjtGeom.mjGEOM_CYLINDER): "cylinder",
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    int(mujoco.mjtGeom.mjGEOM_MESH): "box",
}
VISIBLE_GROUPS = (0, 1, 2)
#: Decimals sent: 0.1 mm, 1e-4 of a rotation matrix entry.
DECIMALS = 4


@dataclass(frozen=True, eq=False)
class TwinGeometry:
    """The drawn geoms of a model: ``geom_ids`` (model ids), their ``shapes``, ``sizes``
    (the shape's half extents / radius, half length), ``rgba``, ``centres`` (the shape's
    centre in the geom frame: a mesh's bounding box is off its origin) and ``dynamic``
    (indices into ``geom_ids`` of the geoms that can move)."""

    geom_ids: np.ndarray
    shapes: tuple[str, ...]
    sizes: np.ndarray
    rgba: np.ndarray
    centres: np.ndarray
    dynamic: np.ndarray

    @classmethod
    def from_model(cls, model: mujoco.MjModel) -> TwinGeometry:
        ids, shapes, sizes, centres = [], [], [], []
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
                centres.append(model.geom_aabb[g, :3].copy())
                sizes.append(model.geom_aabb[g, 3:].copy())
            else:
                centres.append(np.zeros(3))
                sizes.append(model.geom_size[g].copy())
        geom_ids = np.array(ids, dtype=int)
        bodies = model.geom_bodyid[geom_ids]
        moves = (model.body_weldid[bodies] != 0) | (model.body_mocapid[bodies] >= 0)
        return cls(
            geom_ids=geom_ids,
            shapes=tuple(shapes),
            sizes=np.array(sizes, dtype=np.float64).reshape(-1, 3),
            rgba=model.geom_rgba[geom_ids].astype(np.float64),
            centres=np.array(centres, dtype=np.float64).reshape(-1, 3),
            dynamic=np.flatnonzero(moves),
        )

    def poses(self, data: mujoco.MjData, which: np.ndarray | None = None) -> np.ndarray:
        """(n, 12) world poses of the drawn geoms (``which``: indices into ``geom_ids``)."""
        index = np.arange(len(self.geom_ids)) if which is None else which
        ids = self.geom_ids[index]
        R = data.geom_xmat[ids].reshape(-1, 3, 3)
        p = data.geom_xpos[ids] + np.einsum("nij,nj->ni", R, self.centres[index])
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
        }

    def twin_message(self, data: mujoco.MjData, t: float, **status: object) -> dict:
        return {
            "v": PROTOCOL_VERSION,
            "type": "twin",
            "t": round(float(t), 4),
            "pose": np.round(self.poses(data, self.dynamic), DECIMALS).ravel(),
            **status,
        }


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
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
        self.server = server
        self.data = data
        self.period_s = 1.0 / rate_hz
        self.operator = operator
        self.geometry = TwinGeometry.from_model(model)
        self.clock = clock
        self._next = 0.0
        server.publish("scene", self.geometry.scene_message(data, **(info or {})))

    def __call__(self, tick: Tick) -> None:
        now = self.clock()
        if now < self._next:
            return
        self._next = now + self.period_s
        holds = {name: cmd.reason or "hold" for name, cmd in tick.commands.items() if cmd.hold}
        paused = bool(self.operator.paused) if self.operator is not None else False
        message = self.geometry.twin_message(self.data, tick.state.t, paused=paused, holds=holds)
        self.server.publish("twin", message)
