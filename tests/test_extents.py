"""World boxes of geoms (the guard's workspace rule): exact for primitives, containing for meshes."""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.twin.extents import GeomExtents

XML = """
<mujoco>
  <asset>
    <mesh name="tet" vertex="0 0 0  0.1 0 0  0 0.05 0  0 0 0.08"/>
  </asset>
  <worldbody>
    <body><freejoint/><geom type="sphere" size="0.03"/></body>
    <body><freejoint/><geom type="capsule" size="0.02 0.05"/></body>
    <body><freejoint/><geom type="cylinder" size="0.03 0.04"/></body>
    <body><freejoint/><geom type="box" size="0.01 0.02 0.03"/></body>
    <body><freejoint/><geom type="ellipsoid" size="0.01 0.03 0.05"/></body>
    <body><freejoint/><geom type="mesh" mesh="tet"/></body>
  </worldbody>
</mujoco>
"""


def _surface_points(model, g, n=4000, rng=None):
    """Points on the surface of geom ``g`` in its local frame (dense random samples)."""
    rng = rng or np.random.default_rng(0)
    t, s = model.geom_type[g], model.geom_size[g]
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return s[0] * u
    if t == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return u * s[:3]
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        return np.vstack([corners * s[:3], rng.uniform(-1, 1, (n, 3)) * s[:3]])
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        ends = np.where(rng.random((n, 1)) < 0.5, -1.0, 1.0) * np.array([0, 0, s[1]])
        return ends + s[0] * u
    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        angle = rng.uniform(0, 2 * np.pi, n)
        end = np.where(rng.random(n) < 0.5, -s[1], s[1])
        return np.c_[s[0] * np.cos(angle), s[0] * np.sin(angle), end]
    raise AssertionError(t)


def test_boxes_are_tight_for_primitives_and_contain_meshes():
    model = mujoco.MjModel.from_xml_string(XML)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(1)
    extents = GeomExtents(model, np.arange(model.ngeom))
    for _ in range(20):
        for j in range(model.njnt):
            adr = model.jnt_qposadr[j]
            data.qpos[adr : adr + 3] = rng.uniform(-1, 1, 3)
            quat = rng.normal(size=4)
            data.qpos[adr + 3 : adr + 7] = quat / np.linalg.norm(quat)
        mujoco.mj_kinematics(model, data)
        centre, half = extents.compute(data)
        for g in range(model.ngeom):
            R = data.geom_xmat[g].reshape(3, 3)
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                # Compiled mesh vertices are in the geom's frame.
                vertices = model.mesh_vert[model.mesh_vertadr[0] : model.mesh_vertadr[0] + 4]
                world = data.geom_xpos[g] + vertices @ R.T
                assert (world >= centre[g] - half[g] - 1e-9).all()
                assert (world <= centre[g] + half[g] + 1e-9).all()
                continue
            world = data.geom_xpos[g] + _surface_points(model, g, rng=rng) @ R.T
            low, high = world.min(0), world.max(0)
            np.testing.assert_array_less(centre[g] - half[g] - 1e-9, low)
            np.testing.assert_array_less(high, centre[g] + half[g] + 1e-9)
            # Tight: the sampled surface reaches within 1 mm of every face of the box.
            np.testing.assert_allclose(low, centre[g] - half[g], atol=1e-3)
            np.testing.assert_allclose(high, centre[g] + half[g], atol=1e-3)
