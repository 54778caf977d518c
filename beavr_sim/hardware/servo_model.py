"""The one servo motion model every emulator uses (the xArm's joints, Dynamixel and Feetech servos).

:func:`step_towards` is deliberately simple: with torque on, a servo moves towards its goal at a
bounded speed and, optionally, a bounded acceleration (braking so that it stops at the goal),
advanced by wall time. There is no load, gravity, friction or backlash. Positions and speeds are
in the emulator's own units (counts, or radians); it takes one servo (floats) or many (arrays).

It runs on every request an emulator answers (the xArm's in 1 ms substeps), so its cost is part
of every round trip a benchmark measures: one servo is stepped in plain float arithmetic and
many in a handful of array operations, with the same results either way.
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
    if not isinstance(position, np.ndarray) and all(
        np.ndim(x) == 0 for x in (goal, max_speed, velocity, max_accel)
    ):
        return _step_one(
            float(position),
            float(goal),
            float(dt),
            float(max_speed),
            float(velocity),
            float(max_accel),
        )
    return _step_many(position, goal, dt, max_speed, velocity, max_accel)


def _step_one(
    p: float, g: float, dt: float, max_speed: float, v: float, accel: float
) -> tuple[float, float]:
    err = g - p
    if err == 0:
        return p, 0.0
    if math.isfinite(accel):
        # The fastest speed from which the servo can still stop at the goal.
        wanted = math.copysign(min(max_speed, math.sqrt(2.0 * accel * abs(err))), err)
        dv = accel * dt
        wanted = v + min(max(wanted - v, -dv), dv)
    else:
        wanted = math.copysign(max_speed, err)
    step = wanted * dt
    if (step >= err) if err > 0 else (step <= err):
        return g, err / dt
    return p + step, step / dt


def _step_many(position, goal, dt, max_speed, velocity, max_accel) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(position, dtype=np.float64)
    g = np.asarray(goal, dtype=np.float64)
    v = np.asarray(velocity, dtype=np.float64)
    err = g - p
    if np.ndim(max_accel) == 0 and math.isfinite(max_accel):
        wanted = np.copysign(np.minimum(max_speed, np.sqrt((2.0 * max_accel) * np.abs(err))), err)
        dv = max_accel * dt
        wanted = v + np.minimum(np.maximum(wanted - v, -dv), dv)  # (np.clip costs more)
    elif np.ndim(max_accel) == 0:  # infinite: full speed until the goal
        wanted = np.copysign(np.broadcast_to(np.asarray(max_speed, np.float64), err.shape), err)
    else:  # per servo, some finite, some not
        accel = np.asarray(max_accel, dtype=np.float64)
        finite = np.isfinite(accel)
        with np.errstate(invalid="ignore"):
            stop_speed = np.where(finite, np.sqrt(2.0 * accel * np.abs(err)), np.inf)
            wanted = np.copysign(np.minimum(max_speed, stop_speed), err)
            wanted = np.where(finite, v + np.clip(wanted - v, -accel * dt, accel * dt), wanted)
    step = wanted * dt
    # Reached: the step goes at least as far as the goal, in the goal's direction (or no error).
    arrived = np.where(err > 0, step >= err, step <= err)
    arrived |= err == 0
    new_p = np.where(arrived, g, p + step)
    new_v = np.where(arrived, err, step) / dt
    if new_p.ndim == 0:
        return float(new_p), float(new_v)
    return new_p, new_v
