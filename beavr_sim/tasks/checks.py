"""Building blocks of success checkers: rest detection, areas, contacts, latches.

A checker is a function of the simulation state plus the latches documented here; none of
them reads the action or the expert. Latches are updated by the task's ``evaluate`` and reset
by ``initialize_episode``.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

#: "At rest": linear speed below REST_LINEAR_SPEED (m/s) and angular speed below
#: REST_ANGULAR_SPEED (rad/s), continuously for REST_SECONDS of simulated time.
REST_LINEAR_SPEED = 0.02
REST_ANGULAR_SPEED = 0.3
REST_SECONDS = 0.5


@dataclass
class RestTimer:
    """A latch that says whether something has been still for ``hold_s`` seconds."""

    linear_tol: float = REST_LINEAR_SPEED
    angular_tol: float = REST_ANGULAR_SPEED
    hold_s: float = REST_SECONDS
    still_since: float | None = None

    def reset(self) -> None:
        self.still_since = None

    def update(self, time: float, linear_speed: float, angular_speed: float) -> bool:
        """Feed the current speeds at simulated ``time``; True once still for ``hold_s``."""
        if linear_speed < self.linear_tol and angular_speed < self.angular_tol:
            if self.still_since is None or time < self.still_since:
                self.still_since = time
            return time - self.still_since >= self.hold_s - 1e-9
        self.still_since = None
        return False


def inside_rectangle(xy, centre_xy, half_xy, yaw: float = 0.0, margin: float = 0.0) -> bool:
    """Whether point ``xy`` lies in the rectangle (shrunk by ``margin`` on every side)."""
    d = np.asarray(xy[:2], float) - np.asarray(centre_xy[:2], float)
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    return bool(np.all(np.abs(local) <= np.asarray(half_xy, float) - margin))


def in_contact(model: mujoco.MjModel, data: mujoco.MjData, geoms_a, geoms_b) -> bool:
    """Whether any active contact touches one geom of ``geoms_a`` and one of ``geoms_b``."""
    n = data.ncon
    if n == 0:
        return False
    a, b = set(int(g) for g in geoms_a), set(int(g) for g in geoms_b)
    contacts = data.contact  # the contact arrays read once (a struct per contact costs more)
    pairs, excluded = contacts.geom[:n].tolist(), contacts.exclude[:n].tolist()
    for (g1, g2), exclude in zip(pairs, excluded, strict=True):
        if exclude == 0 and ((g1 in a and g2 in b) or (g1 in b and g2 in a)):
            return True
    return False


def up_axis_tilt(R_world_body: np.ndarray, axis: int = 2) -> float:
    """Angle (rad) between the body's ``axis`` and world +z."""
    return float(np.arccos(np.clip(R_world_body[2, axis], -1.0, 1.0)))


def face_up(R_world_body: np.ndarray) -> str:
    """Which face of a cube points up: one of '+x', '-x', '+y', '-y', '+z', '-z'."""
    z_in_body = R_world_body[2, :]  # world +z expressed in the body frame
    k = int(np.argmax(np.abs(z_in_body)))
    return ("+" if z_in_body[k] > 0 else "-") + "xyz"[k]


def robot_geom_ids(model: mujoco.MjModel, prefixes) -> np.ndarray:
    """Geoms of every body whose name starts with one of ``prefixes`` (the effectors)."""
    prefixes = tuple(prefixes)
    ids = [
        g
        for g in range(model.ngeom)
        if (model.body(int(model.geom_bodyid[g])).name or "").startswith(prefixes)
    ]
    return np.array(ids, dtype=int)
