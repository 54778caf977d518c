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

from beavr_sim.twin import kernels


class GeomExtents:
    """Axis-aligned world boxes of a fixed set of geoms: ``centre`` and ``half`` (n x 3)."""

    def __init__(self, model: mujoco.MjModel, geoms: np.ndarray):
        self.geoms = np.asarray(geoms, dtype=np.int64)
        self._types = model.geom_type[self.geoms].astype(np.int64)
        self._size = np.ascontiguousarray(model.geom_size[self.geoms], dtype=np.float64)
        self._aabb = np.ascontiguousarray(model.geom_aabb[self.geoms].reshape(-1, 6))
        self.centre = np.zeros((len(self.geoms), 3))
        self.half = np.zeros((len(self.geoms), 3))

    def compute(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """``(centre, half)``, each n x 3, world frame (arrays owned by this object)."""
        kernels.geom_boxes(
            data.geom_xpos, data.geom_xmat, self.geoms, self._types, self._size, self._aabb,
            self.centre, self.half,
        )  # fmt: skip
        return self.centre, self.half
