"""The twin interface: joint commands in, the simulated robot moves, robot state out.

It owns the env. Commands come in (:meth:`TwinInterface.command`, any number per control
period: one per hand frame in the event-driven runners) and the physics steps one control
period at a time towards the newest of them (:meth:`TwinInterface.step`); :meth:`apply` is
both, once per tick. Each effector's newest command goes into the action at once (an effector
with no command yet, or whose commands stopped, holds its last target: the robot never goes
limp and never jumps); every joint's target is limited to what its speed cap allows in one
control period from the last step's target (the last line against a jump, whatever produced
it; on with the guard off too); the safety guard (:mod:`beavr_sim.twin.guard`) refuses what is
unsafe along the path from the newest accepted target (that effector keeps it). A malformed
command (unknown effector, wrong shape) is logged and counted, never raised: that effector
holds.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from beavr_sim.twin.guard import (
    CollisionGuard,
    GuardConfig,
    GuardVerdict,
    hand_joints,
    max_velocity,
)
from beavr_sim.twin.rate_limit import JointRateLimit
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
        #: The step limit: every joint at its speed cap, each on its own.
        self.rate_limit = JointRateLimit.of(self.max_velocity)
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
        #: The action of the last step (the physics moves from it to :attr:`action`).
        self._stepped = self.action.copy()
        self._moved = False  # a command was checked since the last step
        self._blocked_since_step: tuple[str, ...] = ()

    def reset(self, seed: int | None = None, robot_qpos: np.ndarray | None = None) -> np.ndarray:
        """Reset the env (the robot at ``robot_qpos``, action order, or home); returns the
        measured joint positions (action order)."""
        self.env.reset(seed=seed, options={"robot_qpos": robot_qpos})
        self.action = self.env.agent_pos.astype(np.float64).copy()
        self._stepped = self.action.copy()
        self._moved, self._blocked_since_step = False, ()
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
        """Clamp each joint target to what :attr:`rate_limit` reaches from ``previous`` (the
        last applied action) in one period; count and log (rate-limited) the effectors of
        ``names`` it shortened.

        With the guard on, a non-finite target or one outside the joint's range passes
        unchanged: that is a corrupt command, not a fast one, and the guard refuses it whole
        (``non-finite``, ``joint limit``) rather than the robot moving towards it. With the
        guard off a non-finite target holds that joint."""
        action = self.action
        limited = self.rate_limit.clamp(previous, action, self.dt)
        over = limited.limited
        if self.guard is None:  # nothing else would stop a NaN: that joint holds
            np.copyto(action, previous, where=limited.non_finite)
        else:
            over = over & (action >= self._joint_lower) & (action <= self._joint_upper)
        if not over.any():
            return
        np.copyto(action, limited.target, where=over)
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

    def follow_speed_caps(self, max_velocity: np.ndarray) -> None:
        """Never step faster than ``max_velocity`` (rad/s per action index) either: a mirrored
        rig's device caps, so the hardware can follow every step the twin takes (a twin that
        outran a device left the mirror catching up behind it until its divergence check
        ended the episode)."""
        caps = np.minimum(self.max_velocity, np.asarray(max_velocity, dtype=np.float64))
        self.max_velocity = caps
        self.rate_limit = JointRateLimit.of(caps)

    def apply(self, commands: Mapping[str, JointCommand]) -> TwinState:
        """One control tick: :meth:`command` then :meth:`step` (the virtual-clock replay and
        the single-process loop at one command per tick)."""
        self.command(commands)
        return self.step()

    def command(self, commands: Mapping[str, JointCommand]) -> CommandOutcome:
        """Write the commands into the action the next :meth:`step` takes (the twin's
        actuator targets), at once; any number of times per control period.

        Each joint's target is limited to the target of the last step +- one period at its
        speed cap (the motion the physics makes in that period: the servo model moves the
        reference along that line); the guard refuses what is unsafe along the path from the
        newest accepted action (the path mirrored hardware travels), with its speed and
        acceleration rules measured from the last step's target. A refused effector keeps its
        newest accepted target."""
        commands = {n: c for n, c in commands.items() if self._well_formed(n, c)}
        previous = self.action.copy()
        for name, cmd in commands.items():
            self.action[self.slices[name]] = cmd.positions
        self._limit_steps(self._stepped, commands)
        blocked: tuple[str, ...] = ()
        if self.guard is not None and commands:
            data = self.env.data
            self.guard.set_fixtures(data.mocap_pos, data.mocap_quat)
            self.action, verdict = self.guard.filter(
                self.action,
                previous,
                self.env.data.qpos,
                self.slices,
                reference=self._stepped,
                commit=False,
            )
            blocked = verdict.blocked
            if blocked:
                self.last_refusal = verdict
                for name in blocked:
                    self.guard_blocks[name] = self.guard_blocks.get(name, 0) + 1
            self._moved = True
        accepted = tuple(
            name for name, cmd in commands.items() if not cmd.hold and name not in blocked
        )
        self.commands_applied += len(accepted)
        self._blocked_since_step = tuple(sorted({*self._blocked_since_step, *blocked}))
        # The instant the (guarded) action goes to the actuators: where latency ends.
        self.applied_perf, self.applied_monotonic = time.perf_counter(), time.monotonic()
        return CommandOutcome(accepted=accepted, blocked=blocked)

    def step(self) -> TwinState:
        """Step the env one control period towards the action (the newest guarded targets)."""
        if self.guard is not None:
            if self._moved:
                self.guard.commit(self.action, self._stepped)
            else:
                self.guard.still()
        blocked, self._blocked_since_step, self._moved = self._blocked_since_step, (), False
        self._stepped = self.action.copy()
        terminated, truncated, info = self.env.advance(self.action.astype(np.float32))
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


@dataclass(frozen=True)
class CommandOutcome:
    """What :meth:`TwinInterface.command` did: effectors whose command now drives the twin,
    and those the guard refused (they keep their newest accepted targets)."""

    accepted: tuple[str, ...] = ()
    blocked: tuple[str, ...] = ()
