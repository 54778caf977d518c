"""The mirror's catch-up: the next target toward the twin when the devices are further away
than one period's motion (after a hold, a release, a reset, a recovery), at the catch-up
speed, each target checked by the mirror's own guard; around a refused straight path by a
planned detour (:func:`~beavr_sim.hardware.detour.plan_detour`).

Contract: :meth:`CatchUp.step` never raises on a planning failure (it holds and says why) and
returns the guard's verdict with every target; a target is never further from ``previous`` than
the catch-up speed over the interval. State (the detour's legs, the goal it was planned for,
the last action) belongs to the twin's thread; :meth:`CatchUp.reset` forgets it at an episode's
start.
"""

from __future__ import annotations

import numpy as np

from beavr_sim.hardware.detour import Detour, DetourConfig, plan_detour
from beavr_sim.hardware.mirror.errors import log, one_line
from beavr_sim.twin.guard import CollisionGuard, GuardVerdict
from beavr_sim.twin.rate_limit import JointRateLimit


class CatchUp:
    """Catch-up targets toward the twin's action, guarded (the twin's thread only)."""

    def __init__(self, guard: CollisionGuard, limit: JointRateLimit, qpos: np.ndarray):
        self.guard = guard
        #: The catch-up speeds, per joint.
        self.limit = limit
        #: The model's qpos the guard checks targets in (the joints it is not told stay here).
        self.qpos = qpos
        self.config = DetourConfig()
        #: Every detour planned (found or not), oldest first.
        self.detours: list[Detour] = []
        # The legs still to go, the goal they were planned for, the last action submitted.
        self._legs: list[np.ndarray] = []
        self._goal: np.ndarray | None = None
        self._last_action: np.ndarray | None = None

    def reset(self) -> None:
        """A new episode: no detour under way, no action seen."""
        self._legs, self._goal, self._last_action = [], None, None

    def step(
        self, action: np.ndarray, previous: np.ndarray, interval: float
    ) -> tuple[np.ndarray, GuardVerdict]:
        """The next catch-up target toward ``action`` and the guard's verdict on it.

        Straight at the catch-up speed while the guard accepts that; when it refuses and the
        twin stands still (the same action twice: a sync), a detour is planned (once per goal)
        and its legs are followed instead, each step along its leg at the catch-up speed and
        checked again."""
        if self._goal is not None and not np.array_equal(action, self._goal):
            self._legs, self._goal = [], None  # the twin moved on: that plan is stale
        while self._legs and np.array_equal(previous, self._legs[0]):
            self._legs.pop(0)
        cap = np.asarray(self.limit.max_velocity) * interval
        if self._legs:
            return self._along(self._legs[0], previous, cap)
        target = self.limit.clamp(previous, action, interval).target
        verdict = self.guard.check(target, self.qpos, previous)
        standing = self._last_action is not None and np.array_equal(action, self._last_action)
        self._last_action = action.copy()
        if verdict.ok or not standing or self._goal is not None:
            return target, verdict
        self._goal = action.copy()  # planned once per goal, found or not
        try:
            detour = plan_detour(self.guard, previous, action, self.qpos, self.config)
        except Exception as exc:  # the per-tick path never raises: hold, say why
            log.warning("mirror catch-up: planning a detour failed: %s", one_line(exc))
            return target, verdict
        self.detours.append(detour)
        if not detour.found:
            log.warning(
                "mirror catch-up: the straight path is refused (%s) and %s: the devices hold",
                verdict.reason(),
                detour.reason,
            )
            return target, verdict
        log.info(
            "mirror catch-up: the straight path is refused (%s); going around (%s, %d legs)",
            verdict.reason(),
            detour.method,
            len(detour.waypoints),
        )
        self._legs = [w.copy() for w in detour.waypoints]
        return self._along(self._legs[0], previous, cap)

    def _along(
        self, waypoint: np.ndarray, previous: np.ndarray, cap: np.ndarray
    ) -> tuple[np.ndarray, GuardVerdict]:
        """One catch-up step on the straight leg ``previous`` -> ``waypoint`` (scaled as a
        whole, so the target stays on the leg the planner checked), guarded."""
        d = waypoint - previous
        ratio = float(np.max(np.abs(d) / cap, initial=0.0))
        target = waypoint.copy() if ratio <= 1.0 else previous + d / ratio
        return target, self.guard.check(target, self.qpos, previous)
