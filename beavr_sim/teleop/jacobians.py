"""Jacobians of many body-fixed points at once, from MuJoCo's motion subspaces (``cdof``).

``mj_jac`` computes one point's Jacobian per call: for every degree of freedom k that moves
the point's body, ``jacp[:, k] = lin_k + ang_k x (p - c)``, where ``(ang_k, lin_k)`` is the
dof's motion in the com-based frame (``data.cdof``) and ``c`` the centre of mass of the body's
kinematic tree (``data.subtree_com[body_rootid]``). The same formula written over arrays gives
the Jacobians of all points (and their projections on contact normals) in a handful of numpy
operations, which matters when a QP step needs dozens of them within a millisecond.

``data`` must have been through ``mj_kinematics`` and ``mj_comPos`` (``mink.Configuration``
does both on ``update``).
"""

from __future__ import annotations

import mujoco
import numpy as np

#: Index orders for cross products written over arrays: (a x b) = a[YZX] b[ZXY] - a[ZXY] b[YZX].
_YZX, _ZXY = np.array([1, 2, 0]), np.array([2, 0, 1])


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
        self.root = np.asarray(model.body_rootid)

    def _offsets(self, data: mujoco.MjData, bodies: np.ndarray, points: np.ndarray):
        return points - data.subtree_com[self.root[bodies]]

    def points(self, data: mujoco.MjData, bodies: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(k, 3, nv) Jacobians of ``points`` (k x 3, world) fixed to ``bodies`` (k)."""
        bodies = np.asarray(bodies, dtype=int)
        ang_t, lin_t = data.cdof[:, :3].T, data.cdof[:, 3:].T
        o = self._offsets(data, bodies, points)[:, :, None]
        # Column k: lin_k + ang_k x o, the cross product written over arrays.
        J = ang_t[_YZX] * o[:, _ZXY]
        J -= ang_t[_ZXY] * o[:, _YZX]
        J += lin_t
        J *= self.chain[bodies][:, None, :]
        return J

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
        ang, lin = data.cdof[:, :3], data.cdof[:, 3:]
        k = len(normals)
        bodies = np.concatenate([bodies1, bodies2])
        o = np.concatenate([points1, points2]) - data.subtree_com[self.root[bodies]]
        n = np.concatenate([normals, normals])
        # n . (ang_k x o) = ang_k . (o x n); both points' terms in one product.
        x = o[:, _YZX] * n[:, _ZXY] - o[:, _ZXY] * n[:, _YZX]
        terms = x @ ang.T
        lin_n = normals @ lin.T
        terms[:k] += lin_n
        terms[k:] += lin_n
        terms *= self.chain[bodies]
        return terms[:k] - terms[k:]
