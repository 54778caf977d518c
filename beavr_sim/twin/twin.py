"""The twin interface: joint commands in, the simulated robot moves, robot state out.

It owns the env. Each control tick it composes the newest command of every effector into
one action (an effector with no command yet, or whose commands stopped, holds its last
target: the robot never goes limp and never jumps), limits every joint's step to what its
speed cap allows in one control period (the last line against a jump, whatever produced it;
on with the guard off too), lets the safety guard (:mod:`beavr_sim.twin.guard`) refuse what
is unsafe along that step (that effector holds its last safe target), and steps the env one
control period. A malformed command (unknown effector, wrong shape) is logged and counted,
never raised: that effector holds.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

import numpy as np

from beavr_sim.twin.guard import (
    CollisionGuard,
    GuardConfig,
    GuardVerdict,
    hand_joints,
    max_velocity,
)
from beavr_sim.wire.records import JointCommand, TwinState

log = logging.getLogger(__name__)


class TwinInterface:
    def __init__(self, env, guard: GuardConfig | None = None, use_guard: bool = True):
        self.env = env.unwrapped
        self.slices = self.env.joints.slices
        self.action = self.env.joints.home.astype(np.float64).copy()
        self.commands_applied = 0
        config = guard or GuardConfig()
        #: The control period (s).
        self.dt = 1.0 / self.env.control_hz
        #: Per action index: the speed cap (rad/s) of the step limit (the guard's: arm or hand),
        #: and whether it is a hand joint.
        self.max_velocity = max_velocity(self.env.embodiment, self.env.joints, config)
        self.hand_joints = hand_joints(self.env.embodiment, self.env.joints)
        self._step_cap = self.max_velocity * self.dt
        self._joint_lower, self._joint_upper = self.env.joints.lower, self.env.joints.upper
        #: Ticks on which the step limit shortened an effector's command, per effector name.
        self.step_limited: dict[str, int] = {}
        self.guard: CollisionGuard | None = None
        if use_guard:
            self.guard = CollisionGuard(
                self.env.model, self.env.embodiment, self.env.joints, config, dt=self.dt
            )
        #: The guard's last refusal (None until one happens).
        self.last_refusal: GuardVerdict | None = None
        self.guard_blocks: dict[str, int] = {}
        #: Commands dropped as malformed (unknown effector or wrong shape), per effector name.
        self.malformed: dict[str, int] = {}
        self.applied_perf = self.applied_monotonic = float("nan")

    def reset(self, seed: int | None = None, robot_qpos: np.ndarray | None = None) -> np.ndarray:
        """Reset the env (the robot at ``robot_qpos``, action order, or home); returns the
        measured joint positions (action order)."""
        self.env.reset(seed=seed, options={"robot_qpos": robot_qpos})
        self.action = self.env.agent_pos.astype(np.float64).copy()
        if self.guard is not None:
            self.guard.reset()
        return self.action.copy()

    def _well_formed(self, name: str, cmd: JointCommand) -> bool:
        sl = self.slices.get(name)
        shape = getattr(cmd.positions, "shape", None)
        if sl is not None and shape == (sl.stop - sl.start,):
            return True
        self.malformed[name] = self.malformed.get(name, 0) + 1
        if self.malformed[name] in (1, 10, 100) or self.malformed[name] % 1000 == 0:
            expected = f"shape ({sl.stop - sl.start},)" if sl else f"one of {list(self.slices)}"
            log.warning(
                "dropped malformed command for %r (shape %s; expected %s), %d so far",
                name,
                shape,
                expected,
                self.malformed[name],
            )
        return False

    def _limit_steps(self, previous: np.ndarray, names) -> None:
        """Clamp each joint target to ``previous`` (the last applied action) +- one period at
        its speed cap; count and log (rate-limited) the effectors of ``names`` it shortened.

        With the guard on, a non-finite target or one outside the joint's range passes
        unchanged: that is a corrupt command, not a fast one, and the guard refuses it whole
        (``non-finite``, ``joint limit``) rather than the robot moving towards it. With the
        guard off a non-finite target holds that joint."""
        action = self.action
        if self.guard is None:  # nothing else would stop a NaN: that joint holds
            np.copyto(action, previous, where=~np.isfinite(action))
        low, high = previous - self._step_cap, previous + self._step_cap
        over = (action < low) | (action > high)
        if self.guard is not None:
            over &= (action >= self._joint_lower) & (action <= self._joint_upper)
        if not over.any():
            return
        np.copyto(action, np.clip(action, low, high), where=over)
        for name in names:
            sl = self.slices[name]
            if not over[sl].any():
                continue
            n = self.step_limited[name] = self.step_limited.get(name, 0) + 1
            if n in (1, 10, 100) or n % 1000 == 0:
                i = sl.start + int(np.argmax(over[sl]))
                log.warning(
                    "step limit: %s's command moved %s faster than %.3g rad/s; clamped "
                    "(%d ticks so far)",
                    name,
                    self.env.joints.names[i],
                    self.max_velocity[i],
                    n,
                )

    def apply(self, commands: Mapping[str, JointCommand]) -> TwinState:
        """Write the commands into the action, limit each joint's step to its speed cap, let
        the guard refuse what is unsafe along the step, step one control period."""
        commands = {n: c for n, c in commands.items() if self._well_formed(n, c)}
        previous = self.action.copy()
        for name, cmd in commands.items():
            self.action[self.slices[name]] = cmd.positions
        self._limit_steps(previous, commands)
        blocked: tuple[str, ...] = ()
        if self.guard is not None and commands:
            data = self.env.data
            self.guard.set_fixtures(data.mocap_pos, data.mocap_quat)
            self.action, verdict = self.guard.filter(
                self.action, previous, self.env.data.qpos, self.slices
            )
            blocked = verdict.blocked
            if blocked:
                self.last_refusal = verdict
                for name in blocked:
                    self.guard_blocks[name] = self.guard_blocks.get(name, 0) + 1
        elif self.guard is not None:
            self.guard.still()
        self.commands_applied += sum(
            1 for name, cmd in commands.items() if not cmd.hold and name not in blocked
        )
        # The instant the (guarded) action goes to the actuators: where latency ends.
        self.applied_perf, self.applied_monotonic = time.perf_counter(), time.monotonic()
        _, _, terminated, truncated, info = self.env.step(self.action.astype(np.float32))
        data = self.env.data
        return TwinState(
            t=self.env.elapsed_seconds,
            positions=self.env.agent_pos.astype(np.float64),
            velocities=data.qvel[self.env.joints.qvel_adr].copy(),
            action=self.action.copy(),
            success=bool(info["is_success"]),
            failure=bool(info["is_failure"]),
            terminated=bool(terminated),
            truncated=bool(truncated),
            info=info,
            guard_blocked=bool(blocked),
            guard_blocked_effectors=blocked,
        )
