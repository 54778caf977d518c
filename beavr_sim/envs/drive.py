"""How a stream of joint targets at the control rate becomes actuator controls at the physics rate.

The env's action is one joint-position target per joint per control period. Two drive models:

- **step** (every joint without an :class:`~beavr_sim.robots.parts.ArmServo`: the LEAP hand's
  Dynamixels, the RX-1's Feetech servos): the target goes to the joint's position actuator for
  the whole period, as a goal-position register does on a smart servo.
- **interpolated servo** (:class:`InterpolatedServo`; the xArm in servo mode): the targets are
  samples of a trajectory. Within each period a reference position ``r`` follows the straight
  line from the last target to the new one (a first-order hold: it reaches the new target at
  the end of the period), under the joint's speed and acceleration caps. The actuator gets
  ``r + lead * v`` with ``lead = (kv + damping) / kp``: with the position actuator's force
  ``kp (ctrl - q) - kv qdot`` and the joint's passive damping, that is
  ``kp (r - q) + (kv + damping) (v - qdot)``, a PD on the tracking error with velocity
  feed-forward. The derivative term damps the velocity *error*, so commanded motion is not
  damped (a plain position servo given ``ctrl = target`` lags a ramp by ``rate * kv / kp``).

When a cap binds (a target that moved faster than the joint may, or a sudden change of speed)
the reference falls behind the line and catches up along it, never overshooting it: its speed
relative to the line is at most what lets it brake in time over a distance ``e`` to go
(``v^2 / 2a + v h / 2 <= |e|``) and at most ``|e| / h`` (no overshoot within a physics step ``h``).

What this models and what it does not: the real xArm's servo-mode controller is closed
firmware; we know the joints' speed (pi rad/s) and that the controller tracks the latest
target (the SDK's 20 rad/s^2 caps planned moves, not servo-mode streams; the cap used here is
the guard's, see :data:`beavr_sim.robots.parts.XARM7_SERVO`). Interpolation over the control period is our choice of a
smooth, consistent reference (the guard checks exactly this straight segment), not a fact about
the firmware. ``docs/models.md`` (xArm servo model) gives the numbers.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np


class InterpolatedServo:
    """The reference generator of a set of position-actuated joints (see the module doc).

    ``actuator_ids`` and ``dof_ids`` address the joints in ``model``; ``max_velocity`` and
    ``max_acceleration`` (per joint or one value) are the caps; ``period`` the control period
    and ``n_substeps`` the physics steps per period.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        actuator_ids: np.ndarray,
        dof_ids: np.ndarray,
        max_velocity: np.ndarray | float,
        max_acceleration: np.ndarray | float,
        period: float,
        n_substeps: int,
    ):
        self.actuator_ids = np.asarray(actuator_ids, dtype=np.int64)
        n = len(self.actuator_ids)
        if np.asarray(dof_ids).shape != (n,):
            raise ValueError(f"dof_ids must have {n} entries (one per actuator)")
        if not (period > 0 and n_substeps >= 1):
            raise ValueError(f"period must be > 0 and n_substeps >= 1, got {period}, {n_substeps}")
        self.max_velocity = np.broadcast_to(np.asarray(max_velocity, dtype=np.float64), (n,))
        self.max_acceleration = np.broadcast_to(
            np.asarray(max_acceleration, dtype=np.float64), (n,)
        )
        if not (np.all(self.max_velocity > 0) and np.all(self.max_acceleration > 0)):
            raise ValueError("speed and acceleration caps must be positive")
        kp = model.actuator_gainprm[self.actuator_ids, 0]
        if not np.all(kp > 0):
            raise ValueError("interpolated servo joints need position actuators (gainprm[0] > 0)")
        kv = -model.actuator_biasprm[self.actuator_ids, 2]
        #: Per joint (s): the reference's lead for velocity feed-forward, (kv + damping) / kp.
        self.lead = (kv + model.dof_damping[np.asarray(dof_ids)]) / kp
        self.period = float(period)
        self.n_substeps = int(n_substeps)
        self.h = self.period / self.n_substeps
        self._dv = self.max_acceleration * self.h  # the largest change of speed in one step
        self._inv_h, self._half_h = 1.0 / self.h, 0.5 * self.h
        self._quarter_h2, self._two_over_a = 0.25 * self.h**2, 2.0 / self.max_acceleration
        self.reference = np.zeros(n)
        self.velocity = np.zeros(n)
        self.target = np.zeros(n)
        self._line_start = np.zeros(n)
        self._line_velocity = np.zeros(n)
        self._t = 0.0

    def reset(self, position: np.ndarray) -> None:
        """At rest at ``position``."""
        self.reference = np.array(position, dtype=np.float64)
        self.target = self.reference.copy()
        self._line_start = self.reference.copy()
        self.velocity[:] = 0.0
        self._line_velocity[:] = 0.0
        self._t = 0.0

    @property
    def at_rest(self) -> bool:
        """Whether the reference stands still on a target that does not move this period
        (within 1e-9; it is then snapped onto it): the period needs no per-step controls."""
        if np.any(self._line_velocity) or np.max(np.abs(self.velocity), initial=0.0) > 1e-9:
            return False
        if np.max(np.abs(self.reference - self.target), initial=0.0) > 1e-9:
            return False
        self.reference = self.target.copy()
        self.velocity[:] = 0.0
        return True

    def begin_period(self, target: np.ndarray) -> None:
        """A new target: this period's line runs from the last target to it."""
        self._line_start = self.target
        self.target = np.array(target, dtype=np.float64)
        self._line_velocity = np.clip(
            (self.target - self._line_start) / self.period, -self.max_velocity, self.max_velocity
        )
        self._t = 0.0

    def period_controls(self) -> np.ndarray:
        """The controls of every physics step of this period (``n_substeps`` x joints),
        advancing the reference to the period's end: :meth:`substep` ``n_substeps`` times,
        joint by joint in scalar arithmetic (the joints are independent; far cheaper than
        numpy on a handful of values), in closed form for a joint whose line is within its
        caps from where its reference stands (the usual case: smooth motion)."""
        n, h, period = self.n_substeps, self.h, self.period
        out = np.empty((n, len(self.reference)))
        reference, velocity = self.reference.tolist(), self.velocity.tolist()
        line_start, line_velocity = self._line_start.tolist(), self._line_velocity.tolist()
        targets, leads = self.target.tolist(), self.lead.tolist()
        v_caps, a_caps, dvs = (
            self.max_velocity.tolist(),
            self.max_acceleration.tolist(),
            self._dv.tolist(),
        )
        t0 = self._t
        sqrt, quarter_h2, half_h, inv_h = math.sqrt, self._quarter_h2, self._half_h, self._inv_h
        for j in range(len(reference)):
            r, v, x0, vl, lead = (
                reference[j],
                velocity[j],
                line_start[j],
                line_velocity[j],
                leads[j],
            )
            if (
                t0 == 0.0
                and abs(r - x0) <= 1e-9
                and abs(vl - v) <= dvs[j]
                and abs(targets[j] - x0 - vl * period) <= 1e-12
            ):
                column = x0 + vl * (np.arange(1, n + 1) * h)
                column[-1] = targets[j]
                out[:, j] = column + lead * vl
                reference[j], velocity[j] = targets[j], vl
                continue
            a, dv, v_cap, t = a_caps[j], dvs[j], v_caps[j], t0
            two_over_a = 2.0 / a
            for i in range(n):
                error = x0 + vl * t - r
                distance = abs(error)
                brake = a * (sqrt(quarter_h2 + distance * two_over_a) - half_h)
                step = min(distance * inv_h, brake)
                w = vl + (step if error > 0 else -step if error < 0 else 0.0)
                w = min(max(w, v - dv), v + dv)
                v = min(max(w, -v_cap), v_cap)
                r = r + v * h
                t = min(t + h, period)
                out[i, j] = r + lead * v
            reference[j], velocity[j] = r, v
        self.reference = np.array(reference)
        self.velocity = np.array(velocity)
        self._t = min(t0 + n * h, period)
        return out

    def substep(self) -> np.ndarray:
        """Advance the reference one physics step; the controls for that step."""
        minimum, maximum = np.minimum, np.maximum
        error = self._line_start + self._line_velocity * self._t - self.reference
        distance = np.abs(error)
        # The fastest approach that can still brake in time, in whole physics steps: moving
        # v now and slowing by a h each step after covers v^2 / 2a + v h / 2.
        brake = self.max_acceleration * (
            np.sqrt(self._quarter_h2 + distance * self._two_over_a) - self._half_h
        )
        v = self._line_velocity + np.sign(error) * minimum(distance * self._inv_h, brake)
        v = minimum(maximum(v, self.velocity - self._dv), self.velocity + self._dv)
        v = minimum(maximum(v, -self.max_velocity), self.max_velocity)
        self.velocity = v
        self.reference = self.reference + v * self.h
        self._t = min(self._t + self.h, self.period)
        return self.reference + self.lead * v
