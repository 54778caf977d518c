"""The twin interface: joint commands in, the simulated robot moves, robot state out.

It owns the env. Each control tick it composes the newest command of every effector into
one action (an effector with no command yet, or whose commands stopped, holds its last
target: the robot never goes limp and never jumps) and steps the env one control period.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.teleop.operator import JointCommand


@dataclass(frozen=True)
class TwinState:
    """What the twin publishes after a tick."""

    t: float
    positions: np.ndarray
    velocities: np.ndarray
    action: np.ndarray
    success: bool
    failure: bool
    terminated: bool
    truncated: bool
    info: dict = field(default_factory=dict)
    #: The collision guard refused a command this tick (those effectors held their last
    #: safe target); ``guard_blocked_effectors`` names them.
    guard_blocked: bool = False
    guard_blocked_effectors: tuple[str, ...] = ()


class TwinInterface:
    def __init__(self, env):
        self.env = env.unwrapped
        self.slices = self.env.joints.slices
        self.action = self.env.joints.home.astype(np.float64).copy()
        self.commands_applied = 0

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
            if not cmd.hold:
                self.commands_applied += 1
            self.action[sl] = cmd.positions
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
        )
