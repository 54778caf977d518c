"""The twin interface: joint commands in, the simulated robot moves, robot state out.

It owns the env. Each control tick it composes the newest command of every effector into
one action (an effector with no command yet, or whose commands stopped, holds its last
target: the robot never goes limp and never jumps), lets the safety guard
(:mod:`beavr_sim.twin.guard`) refuse what is unsafe (that effector holds its last safe
target), and steps the env one control period. A malformed command (unknown effector, wrong
shape) is logged and counted, never raised: that effector holds.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

import numpy as np

from beavr_sim.twin.guard import CollisionGuard, GuardConfig, GuardVerdict
from beavr_sim.wire.records import JointCommand, TwinState

log = logging.getLogger(__name__)


class TwinInterface:
    def __init__(self, env, guard: GuardConfig | None = None, use_guard: bool = True):
        self.env = env.unwrapped
        self.slices = self.env.joints.slices
        self.action = self.env.joints.home.astype(np.float64).copy()
        self.commands_applied = 0
        self.guard: CollisionGuard | None = None
        if use_guard:
            self.guard = CollisionGuard(
                self.env.model,
                self.env.embodiment,
                self.env.joints,
                guard or GuardConfig(),
                dt=1.0 / self.env.control_hz,
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

    def apply(self, commands: Mapping[str, JointCommand]) -> TwinState:
        """Write the commands into the action, step one control period."""
        commands = {n: c for n, c in commands.items() if self._well_formed(n, c)}
        previous = self.action.copy()
        for name, cmd in commands.items():
            self.action[self.slices[name]] = cmd.positions
        blocked: tuple[str, ...] = ()
        if self.guard is not None and commands:
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
