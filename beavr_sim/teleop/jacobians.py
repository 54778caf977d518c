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


def _skew(v: np.ndarray) -> np.ndarray:
    """(k, 3) vectors -> (k, 3, 3) matrices with ``S @ x = v x x``."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


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
        ang, lin = data.cdof[:, :3], data.cdof[:, 3:]
        # ang_k x o = -o x ang_k = -[o]x @ ang_k.
        J = lin.T[None] - _skew(self._offsets(data, bodies, points)) @ ang.T[None]
        return J * self.chain[bodies][:, None, :]

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
        # n . (ang_k x o) = ang_k . (o x n); both points' terms in one product.
        o = np.empty((2 * k, 3))
        o[:k] = self._offsets(data, bodies1, points1)
        o[k:] = self._offsets(data, bodies2, points2)
        n = np.concatenate([normals, normals])
        x = np.empty((2 * k, 3))
        x[:, 0] = o[:, 1] * n[:, 2] - o[:, 2] * n[:, 1]
        x[:, 1] = o[:, 2] * n[:, 0] - o[:, 0] * n[:, 2]
        x[:, 2] = o[:, 0] * n[:, 1] - o[:, 1] * n[:, 0]
        terms = (x @ ang.T + (normals @ lin.T)[np.r_[0:k, 0:k]]) * self.chain[
            np.concatenate([bodies1, bodies2])
        ]
        return terms[:k] - terms[k:]
