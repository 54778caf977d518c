"""World-frame bounding boxes of MuJoCo geoms, exact for primitives (vectorised).

For a sphere, capsule, cylinder, box or ellipsoid the box is the tightest axis-aligned box of
the shape in its current pose; other geoms (meshes, ...) get the world box of their local
bounding box (``geom_aabb``), which contains them. Needs ``geom_xpos`` / ``geom_xmat`` from
``mj_kinematics``. Used by the guard's workspace rule: unlike a contact's penetration depth,
a box's lowest point does not depend on which side of a thin table a link has passed.
"""

from __future__ import annotations

import mujoco
import numpy as np

_T = mujoco.mjtGeom


class GeomExtents:
    """Axis-aligned world boxes of a fixed set of geoms: ``centre`` and ``half`` (n x 3)."""

    def __init__(self, model: mujoco.MjModel, geoms: np.ndarray):
        self.geoms = np.asarray(geoms, dtype=int)
        types = model.geom_type[self.geoms]
        self._size = model.geom_size[self.geoms].copy()
        self._aabb = model.geom_aabb[self.geoms].reshape(-1, 6).copy()
        self._by_type = {
            t: np.flatnonzero(types == t)
            for t in (_T.mjGEOM_SPHERE, _T.mjGEOM_CAPSULE, _T.mjGEOM_CYLINDER, _T.mjGEOM_BOX)
        }
        self._by_type["ellipsoid"] = np.flatnonzero(types == _T.mjGEOM_ELLIPSOID)
        known = np.concatenate(list(self._by_type.values()))
        self._other = np.setdiff1d(np.arange(len(self.geoms)), known)

    def compute(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """``(centre, half)``, each n x 3, world frame."""
        R = data.geom_xmat[self.geoms].reshape(-1, 3, 3)
        centre = data.geom_xpos[self.geoms].copy()
        half = np.empty_like(centre)
        s = self._size
        i = self._by_type[_T.mjGEOM_SPHERE]
        half[i] = s[i, :1]
        i = self._by_type[_T.mjGEOM_CAPSULE]
        half[i] = np.abs(R[i, :, 2]) * s[i, 1:2] + s[i, :1]
        i = self._by_type[_T.mjGEOM_CYLINDER]
        axis = R[i, :, 2]
        half[i] = np.abs(axis) * s[i, 1:2] + s[i, :1] * np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0))
        i = self._by_type[_T.mjGEOM_BOX]
        half[i] = np.einsum("nkj,nj->nk", np.abs(R[i]), s[i])
        i = self._by_type["ellipsoid"]
        half[i] = np.sqrt(np.einsum("nkj,nj->nk", R[i] ** 2, s[i] ** 2))
        i = self._other
        if len(i):
            centre[i] += np.einsum("nkj,nj->nk", R[i], self._aabb[i, :3])
            half[i] = np.einsum("nkj,nj->nk", np.abs(R[i]), self._aabb[i, 3:])
        return centre, half
