"""Jacobians of many body-fixed points at once, from MuJoCo's motion subspaces (``cdof``).

``mj_jac`` computes one point's Jacobian per call: for every degree of freedom k that moves
the point's body, ``jacp[:, k] = lin_k + ang_k x (p - c)``, where ``(ang_k, lin_k)`` is the
dof's motion in the com-based frame (``data.cdof``) and ``c`` the centre of mass of the body's
kinematic tree (``data.subtree_com[body_rootid]``). The same formula, compiled
(:mod:`beavr_sim.operator.kernels`), gives the Jacobians of all points (and their projections on
contact normals) in one call, which matters when a QP step needs dozens of them within a
millisecond.

``data`` must have been through ``mj_kinematics`` and ``mj_comPos`` (``mink.Configuration``
does both on ``update``).
"""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.operator import kernels


class PointJacobians:
    """Translational Jacobians of points fixed to bodies of ``model``."""

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        #: ``chain[b, k]`` = 1 when dof k moves body b (a dof of b or of an ancestor).
        chain = np.zeros((model.nbody, model.nv))
        for b in range(model.nbody):
            a = b
            while a > 0:
                start = int(model.body_dofadr[a])
                chain[b, start : start + int(model.body_dofnum[a])] = 1.0
                a = int(model.body_parentid[a])
        self.chain = chain
        self.root = np.asarray(model.body_rootid, dtype=np.int64)

    def points(self, data: mujoco.MjData, bodies: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(k, 3, nv) Jacobians of ``points`` (k x 3, world) fixed to ``bodies`` (k)."""
        bodies = np.asarray(bodies, dtype=np.int64)
        points = np.asarray(points, dtype=np.float64)
        out = np.empty((bodies.size, 3, self.model.nv))
        return kernels.point_jacobians(
            data.cdof, data.subtree_com, self.root, self.chain, bodies, points, out
        )

    def normal_rows(
        self,
        data: mujoco.MjData,
        normals: np.ndarray,
        bodies1: np.ndarray,
        points1: np.ndarray,
        bodies2: np.ndarray,
        points2: np.ndarray,
    ) -> np.ndarray:
        """(k, nv) rows ``n^T (J(p1) - J(p2))``: the rate at which each contact's separation
        along ``normals`` (geom 1 -> geom 2) shrinks per unit joint velocity."""
        f64, i64 = np.float64, np.int64
        return kernels.normal_rows(
            data.cdof,
            data.subtree_com,
            self.root,
            self.chain,
            np.ascontiguousarray(normals, dtype=f64),
            np.asarray(bodies1, dtype=i64),
            np.ascontiguousarray(points1, dtype=f64),
            np.asarray(bodies2, dtype=i64),
            np.ascontiguousarray(points2, dtype=f64),
        )
