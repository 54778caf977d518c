"""The twin interface: joint commands in, the simulated robot moves, robot state out.

It owns the env. Each control tick it composes the newest command of every effector into
one action (an effector with no command yet, or whose commands stopped, holds its last
target: the robot never goes limp and never jumps), lets the collision guard
(:mod:`beavr_sim.twin.guard`) refuse what would collide (that effector holds its last safe
target), and steps the env one control period.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from beavr_sim.twin.guard import CollisionGuard, GuardConfig, GuardVerdict
from beavr_sim.wire.records import JointCommand, TwinState


class TwinInterface:
    def __init__(self, env, guard: GuardConfig | None = None, use_guard: bool = True):
        self.env = env.unwrapped
        self.slices = self.env.joints.slices
        self.action = self.env.joints.home.astype(np.float64).copy()
        self.commands_applied = 0
        self.guard: CollisionGuard | None = None
        if use_guard:
            self.guard = CollisionGuard(
                self.env.model, self.env.embodiment, self.env.joints, guard or GuardConfig()
            )
        #: The guard's last refusal (None until one happens).
        self.last_refusal: GuardVerdict | None = None
        self.guard_blocks: dict[str, int] = {}
        self.applied_perf = self.applied_monotonic = float("nan")

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Reset the env; returns the measured joint positions (action order)."""
        self.env.reset(seed=seed)
        self.action = self.env.agent_pos.astype(np.float64).copy()
        return self.action.copy()

    def apply(self, commands: Mapping[str, JointCommand]) -> TwinState:
        """Write the commands into the action, step one control period."""
        for name, cmd in commands.items():
            if name not in self.slices:
                raise ValueError(f"command for unknown effector {name!r}; have {list(self.slices)}")
            sl = self.slices[name]
            if cmd.positions.shape != (sl.stop - sl.start,):
                raise ValueError(
                    f"command for {name} has shape {cmd.positions.shape}, "
                    f"expected ({sl.stop - sl.start},)"
                )
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
