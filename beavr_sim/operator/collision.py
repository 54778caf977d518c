"""Collision avoidance rows for the operator's QPs (arm IK and LEAP retargeting): mink's
``CollisionAvoidanceLimit`` constraint, with every distance query of a tick done in one call.

mink calls ``mj_geomDistance`` once per geom pair from Python; at 20-30 pairs per tick that
was most of the retargeting time. :class:`CollisionLimit` instead compiles a private
*distance model* from the robot's spec: no geom collides except the watched pairs, declared
as explicit contact pairs whose margin is the pair's detection distance, so one
``mj_collision`` (C: broadphase and narrowphase of every pair) returns a contact for each
pair closer than its detection distance, with the signed distance, the midpoint and the
normal. Box-box pairs are queried on convex-mesh twins of the boxes: MuJoCo's box-box
collider reports contacts for penetration but misses boxes that are apart yet inside the
margin, while the general convex collider (the one ``mj_geomDistance`` uses) gets those.

The rows are mink's: for a pair at distance ``d`` with normal ``n`` (geom 1 -> geom 2) and
witness points ``p1``, ``p2``, ``-n^T (J(p2) - J(p1)) dq <= gain (d - margin) / dt`` (0 once
within the margin), kept only for pairs within their detection distance. ``J(p)`` is the
point Jacobian from the dofs' motion subspaces (:mod:`beavr_sim.operator.jacobians`); selection
and rows are one compiled call (:func:`beavr_sim.operator.kernels.contact_rows`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import mink
import mujoco
import numpy as np

from beavr_sim.operator import kernels
from beavr_sim.operator.jacobians import PointJacobians

_BOX = mujoco.mjtGeom.mjGEOM_BOX


def distance_model(
    spec: mujoco.MjSpec,
    model: mujoco.MjModel,
    pairs: Sequence[tuple[int, int]],
    detection: Sequence[float],
) -> tuple[mujoco.MjModel, np.ndarray]:
    """Compile ``spec`` (a fresh, uncompiled twin of the spec ``model`` came from; it is
    changed) so that only ``pairs`` (geom ids of ``model``) collide, each as an explicit pair
    with margin ``detection[i]``.

    Returns the distance model (same bodies and joints as ``model``) and its pair lookup:
    ``lookup[g1, g2]`` is the index in ``pairs`` of a contact between distance-model geoms
    ``g1`` and ``g2`` (-1 for none).
    """
    s = spec
    geoms = list(s.geoms)
    if len(geoms) != model.ngeom:
        raise ValueError(
            f"spec has {len(geoms)} geoms but the model {model.ngeom}: pass the spec the "
            "model was compiled from"
        )
    for i, geom in enumerate(geoms):
        geom.contype = geom.conaffinity = 0
        if not geom.name:
            geom.name = f"__geom{i}"
    names = [g.name for g in geoms]
    boxes = {
        g
        for a, b in pairs
        if model.geom_type[a] == _BOX and model.geom_type[b] == _BOX
        for g in (a, b)
    }
    twin: dict[int, str] = {}
    for g in sorted(boxes):
        body = model.body(model.geom_bodyid[g]).name
        if not body:
            raise ValueError(f"geom {names[g]!r} is in an unnamed body; name it")
        hx, hy, hz = model.geom_size[g]
        corners = itertools.product((-hx, hx), (-hy, hy), (-hz, hz))
        mesh = s.add_mesh(name=f"__box_mesh{g}", uservert=np.ravel(list(corners)).tolist())
        twin[g] = f"__box_twin{g}"
        s.body(body).add_geom(
            name=twin[g],
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=mesh.name,
            pos=model.geom_pos[g].tolist(),
            quat=model.geom_quat[g].tolist(),
            contype=0,
            conaffinity=0,
            density=0.0,
            group=5,
            rgba=[0, 0, 0, 0],
        )
    for (a, b), margin in zip(pairs, detection, strict=True):
        both_boxes = a in boxes and b in boxes
        s.add_pair(
            geomname1=twin[a] if both_boxes else names[a],
            geomname2=twin[b] if both_boxes else names[b],
            margin=float(margin),
            gap=0.0,
        )
    dmodel = s.compile()
    if dmodel.nbody != model.nbody or dmodel.nq != model.nq:
        raise ValueError("the spec does not match the model (bodies or joints differ)")
    # The compiler may reorder pairs: map each back to its index in ``pairs`` by geom names.
    original = {name: g for g, name in enumerate(names)} | {n: g for g, n in twin.items()}
    index = {frozenset(p): i for i, p in enumerate(pairs)}
    lookup = np.full((dmodel.ngeom, dmodel.ngeom), -1, dtype=np.int64)
    for i in range(dmodel.npair):
        g1, g2 = int(dmodel.pair_geom1[i]), int(dmodel.pair_geom2[i])
        key = frozenset((original[dmodel.geom(g1).name], original[dmodel.geom(g2).name]))
        lookup[g1, g2] = lookup[g2, g1] = index[key]
    return dmodel, lookup


class CollisionLimit(mink.CollisionAvoidanceLimit):
    """mink's collision avoidance limit (same rows, up to the distance solver's tolerance),
    with all distance queries of a tick in one ``mj_collision`` on a private distance model.

    ``spec``: a fresh, uncompiled twin of the spec ``model`` was compiled from; the distance
    model is built from it (it is changed, so do not reuse it).
    ``pair_detection_distance(geom1, geom2)``: detection distance per geom pair, for pairs
    that can approach each other at different speeds (default: ``collision_detection_distance``
    for all). ``closest_only``: keep only each pair's closest contact (mink's choice: fewer
    QP rows) rather than every contact MuJoCo reports for it. ``recovery``: fraction of a
    pair's intrusion into ``minimum_distance_from_collisions`` that a step must undo (0,
    mink's rows: only no deeper; see :func:`~beavr_sim.operator.kernels.contact_rows`). Other
    arguments as ``mink.CollisionAvoidanceLimit``.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        geom_pairs,
        *,
        spec: mujoco.MjSpec,
        pair_detection_distance: Callable[[int, int], float] | None = None,
        closest_only: bool = False,
        recovery: float = 0.0,
        **kwargs,
    ):
        super().__init__(model, geom_pairs, broadphase=False, **kwargs)
        self.closest_only = bool(closest_only)
        if not (np.isfinite(recovery) and 0.0 <= recovery <= 1.0):
            raise ValueError(f"recovery must be in [0, 1], got {recovery!r}")
        self.recovery = float(recovery)
        pairs = [(int(a), int(b)) for a, b in self.geom_id_pairs]
        self._distmax = np.array(
            [
                self.collision_detection_distance
                if pair_detection_distance is None
                else pair_detection_distance(a, b)
                for a, b in pairs
            ]
        )
        self.distance_model, self._lookup = distance_model(spec, model, pairs, self._distmax)
        if self.closest_only:
            # One contact per pair is all that is kept: skip MuJoCo's extra contacts on
            # flat convex faces (multi-CCD), which cost narrowphase time for nothing.
            self.distance_model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_MULTICCD
        self._ddata = mujoco.MjData(self.distance_model)
        self._geom_body = self.distance_model.geom_bodyid.astype(np.int64)
        self._npairs = len(pairs)
        self._jacobians = PointJacobians(model)
        self._allocate(max(self._npairs, 16))
        self._compile()

    def _allocate(self, capacity: int) -> None:
        """Row arrays for up to ``capacity`` contacts (they grow when a tick has more)."""
        self._pairs_out = np.zeros(capacity, dtype=np.int64)
        self._dists_out = np.zeros(capacity)
        self._rows_out = np.zeros((capacity, self.model.nv))
        self._h_out = np.zeros(capacity)

    def _compile(self) -> None:
        """Compile (or load) the rows kernel for both array layouts MuJoCo's contact fields
        come in: contiguous for 0 or 1 contacts, strided views into the contact structs for
        more. Otherwise the first tick that sees the other layout would stall to compile."""
        data = mujoco.MjData(self.model)
        mujoco.mj_kinematics(self.model, data)
        mujoco.mj_comPos(self.model, data)
        g1, g2 = self.distance_model.pair_geom1[0], self.distance_model.pair_geom2[0]
        for n in (0, 2):  # strided like the contact fields: every other element
            geom = np.zeros((n, 4), dtype=np.int32)[:, :2]
            geom[:] = g1, g2
            jac = self._jacobians
            kernels.contact_rows(
                geom, np.zeros(2 * n)[::2], np.ones((n, 18))[:, :9], np.zeros((n, 6))[:, :3],
                self._lookup, self._geom_body, self._npairs, self.closest_only,
                data.cdof, data.subtree_com, jac.root, jac.chain, 1.0, 0.0, 0.0, 1.0,
                self._pairs_out, self._dists_out, self._rows_out, self._h_out, self.recovery,
            )  # fmt: skip

    def distances(self, configuration: mink.Configuration):
        """Contacts of the pairs within their detection distance at ``configuration``:
        ``(pair indices, distances, normals (geom 1 -> geom 2), witness points on geom 1, on
        geom 2, body of geom 1, body of geom 2)``, one row per contact (a pair may have
        several, e.g. a capsule lying along a box face: each is a valid constraint)."""
        ddata = self._query(configuration)
        contact = ddata.contact
        geom, dist = contact.geom, contact.dist
        keep, pair = kernels.select_contacts(
            geom, dist, self._lookup, self._npairs, self.closest_only
        )
        geom, dist = geom[keep], dist[keep]
        normal, pos = contact.frame[keep, :3], contact.pos[keep]
        half = (0.5 * dist)[:, None] * normal
        body = self._geom_body[geom]
        return pair, dist, normal, pos - half, pos + half, body[:, 0], body[:, 1]

    def _query(self, configuration: mink.Configuration) -> mujoco.MjData:
        """The distance model's data after one ``mj_collision`` at ``configuration``."""
        dmodel, ddata = self.distance_model, self._ddata
        ddata.qpos[:] = configuration.data.qpos
        if dmodel.nmocap:  # static obstacles placed by the caller (see operator.obstacles)
            ddata.mocap_pos[:] = configuration.data.mocap_pos
            ddata.mocap_quat[:] = configuration.data.mocap_quat
        mujoco.mj_kinematics(dmodel, ddata)
        mujoco.mj_collision(dmodel, ddata)
        return ddata

    def active_rows(
        self, configuration: mink.Configuration, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One row per contact of the pairs within their detection distance: ``(pair
        indices, G rows, h)``, so that ``G @ dq <= h``. The arrays are views of this limit's
        buffers, valid until its next query (copy them to keep them)."""
        hits, _, rows, h = self._rows(configuration, dt)
        return hits, rows, h

    def _rows(self, configuration: mink.Configuration, dt: float):
        data = configuration.data  # kinematics and comPos done
        ddata = self._query(configuration)
        if ddata.ncon > self._h_out.shape[0]:
            self._allocate(2 * ddata.ncon)
        contact = ddata.contact
        jac = self._jacobians
        k = kernels.contact_rows(
            contact.geom, contact.dist, contact.frame, contact.pos,
            self._lookup, self._geom_body, self._npairs, self.closest_only,
            data.cdof, data.subtree_com, jac.root, jac.chain,
            float(self.gain), float(self.minimum_distance_from_collisions),
            float(self.bound_relaxation), float(dt),
            self._pairs_out, self._dists_out, self._rows_out, self._h_out, self.recovery,
        )  # fmt: skip
        return self._pairs_out[:k], self._dists_out[:k], self._rows_out[:k], self._h_out[:k]

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float):
        """mink's form: one row per pair (its closest contact), +inf for pairs out of range."""
        hits, dist, rows, h = self._rows(configuration, dt)
        order = np.lexsort((-dist, hits))  # per pair, the closest contact last: it wins below
        hits, rows, h = hits[order], rows[order], h[order]
        G = np.zeros((self.max_num_contacts, self.model.nv))
        upper = np.full(self.max_num_contacts, np.inf)
        G[hits], upper[hits] = rows, h
        return mink.Constraint(G=G, h=upper)
