"""The one servo motion model every emulator uses (the xArm's joints, Dynamixel and Feetech servos).

:func:`step_towards` is deliberately simple: with torque on, a servo moves towards its goal at a
bounded speed and, optionally, a bounded acceleration (braking so that it stops at the goal),
advanced by wall time. There is no load, gravity, friction or backlash. Positions and speeds are
in the emulator's own units (counts, or radians); it takes one servo (floats) or many (arrays).
"""

from __future__ import annotations

import math

import numpy as np


def step_towards(
    position,
    goal,
    dt: float,
    max_speed,
    velocity=0.0,
    max_accel=math.inf,
):
    """One step of the servo model: ``(position, velocity)`` after ``dt`` seconds of moving from
    ``position`` towards ``goal`` at most ``max_speed`` (units/s), changing speed by at most
    ``max_accel`` (units/s^2) and braking to stop at the goal. A step that reaches the goal ends
    exactly on it. With ``max_accel`` infinite, the speed is ``max_speed`` until the goal.
    Floats in, floats out; arrays (one entry per servo, broadcast) in, arrays out.
    """
    if dt <= 0:
        return position, velocity
    p = np.asarray(position, dtype=np.float64)
    g = np.asarray(goal, dtype=np.float64)
    v = np.asarray(velocity, dtype=np.float64)
    accel = np.asarray(max_accel, dtype=np.float64)
    err = g - p
    with np.errstate(invalid="ignore"):
        # The fastest speed from which the servo can still stop at the goal.
        stop_speed = np.where(np.isfinite(accel), np.sqrt(2.0 * accel * np.abs(err)), np.inf)
        wanted = np.copysign(np.minimum(max_speed, stop_speed), err)
        dv = accel * dt
        wanted = np.where(np.isfinite(accel), v + np.clip(wanted - v, -dv, dv), wanted)
        step = wanted * dt
        arrived = (err == 0) | ((step >= err) & (err > 0)) | ((step <= err) & (err < 0))
        new_p = np.where(arrived, g, p + step)
        new_v = np.where(err == 0, 0.0, np.where(arrived, err / dt, step / dt))
    if new_p.ndim == 0:
        return float(new_p), float(new_v)
    return new_p, new_v
