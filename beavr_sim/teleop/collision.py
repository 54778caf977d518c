"""A faster drop-in for ``mink.CollisionAvoidanceLimit`` (same constraint rows), shared by the
operator's arm IK and the LEAP retargeting, where it dominated the per-tick time."""

from __future__ import annotations

import mink
import mujoco
import numpy as np


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (k, 3) arrays."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


class CollisionLimit(mink.CollisionAvoidanceLimit):
    """mink's collision avoidance limit, computed faster (the same constraint rows):

    - broadphase: world-aligned boxes around each geom's oriented bounding box instead of
      bounding spheres (neighbouring fingers are always within each other's spheres); like
      mink's, it only drops pairs farther apart than their detection distance;
    - a detection distance per pair (``pair_detection_distance(geom1, geom2)``), for pairs
      that can approach each other at different speeds;
    - contact Jacobians from one ``mj_jacBody`` per body involved, shifted to the witness
      points and projected on the normals for all pairs at once, instead of two ``mj_jac``
      calls and a product per pair: n^T J(p) = n^T Jp_body - (n x (p - x_body))^T Jr_body.
    """

    def __init__(self, model: mujoco.MjModel, geom_pairs, pair_detection_distance=None, **kwargs):
        super().__init__(model, geom_pairs, broadphase=True, **kwargs)
        self.broadphase_min_pairs = 0
        pairs = np.array(self.geom_id_pairs, dtype=int).reshape(-1, 2)
        self._pairs = pairs
        #: Detection distance of each pair (callable geom1, geom2 -> metres; default: all
        #: the limit's own).
        self._distmax = np.array(
            [
                self.collision_detection_distance
                if pair_detection_distance is None
                else pair_detection_distance(int(a), int(b))
                for a, b in pairs
            ]
        )
        self._geoms, inverse = np.unique(pairs, return_inverse=True)
        self._pair1, self._pair2 = inverse.reshape(-1, 2).T
        self._aabb_centre = model.geom_aabb[self._geoms, :3]
        self._aabb_half = model.geom_aabb[self._geoms, 3:]
        self._body1 = model.geom_bodyid[pairs[:, 0]]
        self._body2 = model.geom_bodyid[pairs[:, 1]]
        self._bodies = np.unique(np.concatenate([self._body1, self._body2]))
        self._jac = np.zeros((model.nbody, 6, model.nv))  # per body: jacp over jacr
        self._distmax_list = self._distmax.tolist()
        self._pair_list = [(int(a), int(b)) for a, b in pairs]
        self._fromto_all = np.zeros((len(pairs), 6))
        self._dist = np.zeros(len(pairs))
        self._hits = np.zeros(len(pairs), dtype=int)

    def _broadphase_survivors(self, data: mujoco.MjData) -> list[int]:
        R_world_geom = data.geom_xmat[self._geoms].reshape(-1, 3, 3)
        centre = (
            data.geom_xpos[self._geoms] + (R_world_geom @ self._aabb_centre[:, :, None])[:, :, 0]
        )
        half = (np.abs(R_world_geom) @ self._aabb_half[:, :, None])[:, :, 0]
        gap = (
            np.abs(centre[self._pair1] - centre[self._pair2])
            - half[self._pair1]
            - half[self._pair2]
        )
        return np.flatnonzero(gap.max(axis=1) <= self._distmax).tolist()

    def active_rows(
        self, configuration: mink.Configuration, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Only the pairs within their detection distance: ``(pair indices, G rows, h)``, so
        that ``G @ dq <= h`` (in :meth:`compute_qp_inequalities` the other rows are +inf)."""
        model, data = self.model, configuration.data
        distmax_all = self._distmax_list
        geom_distance, pair_list = mujoco.mj_geomDistance, self._pair_list
        fromto_all, dist_all, hits_all = self._fromto_all, self._dist, self._hits
        k = 0
        for idx in self._broadphase_survivors(data):
            g1, g2 = pair_list[idx]
            distmax = distmax_all[idx]
            dist = geom_distance(model, data, g1, g2, distmax, fromto_all[k])
            if abs(dist - distmax) < 1e-12:
                continue
            hits_all[k], dist_all[k] = idx, dist
            k += 1
        if k == 0:
            return hits_all[:0].copy(), np.zeros((0, model.nv)), np.zeros(0)
        hits, dist, fromto = hits_all[:k].copy(), dist_all[:k], fromto_all[:k]
        b1, b2 = self._body1[hits], self._body2[hits]
        jac = self._jac
        for body in set(b1.tolist()) | set(b2.tolist()):
            mujoco.mj_jacBody(model, data, jac[body, :3], jac[body, 3:], body)
        p1, p2 = fromto[:, :3], fromto[:, 3:]
        normal = p2 - p1
        length = np.sqrt((normal * normal).sum(axis=1))
        ok = length > 1e-15
        normal[ok] /= length[ok, None]
        normal[~ok] = (1.0, 0.0, 0.0)  # as mju_normalize3 does for a zero vector
        # n^T J(p) = n^T Jp_body - (n x (p - x_body))^T Jr_body, for both witness points.
        v1, v2 = np.empty((k, 1, 6)), np.empty((k, 1, 6))
        v1[:, 0, :3], v2[:, 0, :3] = -normal, normal
        v1[:, 0, 3:] = _cross_rows(normal, p1 - data.xpos[b1])
        v2[:, 0, 3:] = -_cross_rows(normal, p2 - data.xpos[b2])
        rows = (v1 @ jac[b1])[:, 0] + (v2 @ jac[b2])[:, 0]
        min_dist = self.minimum_distance_from_collisions
        h = (
            np.where(dist > min_dist, self.gain * (dist - min_dist) / dt, 0.0)
            + self.bound_relaxation
        )
        rows *= np.where(dist >= 0, -1.0, 1.0)[:, None]
        return hits, rows, h

    def compute_qp_inequalities(self, configuration: mink.Configuration, dt: float):
        hits, rows, h = self.active_rows(configuration, dt)
        G = np.zeros((self.max_num_contacts, self.model.nv))
        upper = np.full(self.max_num_contacts, np.inf)
        G[hits], upper[hits] = rows, h
        return mink.Constraint(G=G, h=upper)
