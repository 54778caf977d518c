"""The in-process teleop loop: source -> validator -> operator -> twin, one tick at a time.

Used by tests, deterministic replay and the single-process CLI. On the virtual clock
(``real_time=False``) tick k happens at t = k * dt whatever the machine's speed, and the
source delivers the frames stamped up to that time: a replay is bit-for-bit repeatable. In
real time the loop sleeps to the control rate and the clock is ``time.monotonic()``. Paced
(``paced=True``, virtual clock): the virtual clock's ticks, slept to the control rate - the
same deterministic replay, at the speed hardware moves (a mirrored trace replay).

Latency is measured per applied (non-hold, not refused) command from the moment its hand frame
entered the pipeline (received by the detector: ``t_receive`` in real time, the poll on the
virtual clock) to the moment the command, past the collision guard, is handed to the twin's
actuators.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from beavr_sim.headset.sources import HandSource
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.operator.operator import Operator
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import Tick, TickListener


@dataclass
class TeleopSummary:
    task: str
    embodiment: str
    success: bool
    frames_received: int
    frames_rejected: int
    commands_applied: int
    duration_s: float
    latency_ms: dict
    rejected_by_reason: dict = field(default_factory=dict)
    holds: dict = field(default_factory=dict)
    operator: dict = field(default_factory=dict)
    ticks: int = 0
    loop_rate_hz: float | None = None
    processes: dict = field(default_factory=dict)
    #: Commands the collision guard refused, per effector.
    guard_blocks: dict = field(default_factory=dict)
    #: Per mirrored device (teleop --mirror-hardware): connected, commands sent and refused,
    #: holds, largest divergence from the twin, errors.
    hardware: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


def _percentiles(values_ms: Sequence[float]) -> dict:
    if not values_ms:
        return {"p50": None, "p99": None, "n": 0}
    a = np.asarray(values_ms)
    return {
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "n": len(a),
    }


class TeleopLoop:
    def __init__(
        self,
        twin: TwinInterface,
        operator: Operator,
        source: HandSource,
        *,
        validator: StreamValidator | None = None,
        real_time: bool = False,
        paced: bool = False,
        listeners: Sequence[TickListener] = (),
    ):
        self.twin = twin
        self.operator = operator
        self.source = source
        self.validator = validator or StreamValidator()
        self.real_time = bool(real_time)
        #: Sleep to the control rate on the virtual clock (real time implies it).
        self.paced = bool(paced) or self.real_time
        self.listeners = list(listeners)
        self.dt = 1.0 / twin.env.control_hz
        self.frames_received = 0
        self.latencies_ms: list[float] = []
        self.holds: dict[str, int] = {}
        self.ticks = 0
        self._t0 = 0.0
        #: Seed of the current episode (reset with the same seed re-runs the same layout).
        self.seed: int | None = None
        #: How many times the loop was reset (a reset during :meth:`run` starts the wait for
        #: the end of the source over).
        self.resets = 0

    # ------------------------------------------------------------------ control
    def reset(self, seed: int | None = None, robot_qpos: np.ndarray | None = None) -> None:
        """Reset the twin (new episode; the robot at ``robot_qpos`` or home) and re-home the
        operator from the measured joints."""
        self.seed = seed
        self.resets += 1
        q = self.twin.reset(seed, robot_qpos)
        self.operator.reset(q, self.twin.slices)
        self.ticks = 0
        self._t0 = time.monotonic()

    def replace_source(self, source: HandSource) -> None:
        """A new stream (e.g. a trace played again from its start): its timestamps start over,
        so the validator's ordering check starts over too."""
        self.source = source
        self.validator.reset()

    def now(self) -> float:
        return time.monotonic() if self.real_time else self.ticks * self.dt

    # ------------------------------------------------------------------ one tick
    def tick(self) -> Tick:
        now = self.now()
        poll_wall = time.perf_counter()
        used = []
        for frame in self.source.poll(now):
            self.frames_received += 1
            if self.source.validates or self.validator.check(frame) is None:
                self.operator.observe(frame)
                used.append(frame)
        commands = self.operator.command(now)
        for cmd in commands.values():
            if cmd.hold:
                self.holds[cmd.reason] = self.holds.get(cmd.reason, 0) + 1
        state = self.twin.apply(commands)
        for name in state.guard_blocked_effectors:  # continue from where the robot was held
            self.operator.resync(name, state.action[self.twin.slices[name]])
        if used:
            for cmd in commands.values():
                if cmd.hold or cmd.effector in state.guard_blocked_effectors:
                    continue
                if self.real_time:
                    self.latencies_ms.append((self.twin.applied_monotonic - cmd.t_receive) * 1e3)
                else:
                    self.latencies_ms.append((self.twin.applied_perf - poll_wall) * 1e3)
        self.ticks += 1
        tick = Tick(t=now, frames=tuple(used), commands=commands, state=state)
        for listener in self.listeners:
            listener(tick)
        return tick

    # ------------------------------------------------------------------ episode
    def run(
        self,
        max_seconds: float | None = None,
        stop_on_success: bool = True,
        tail_seconds: float = 2.0,
        progress: Callable[[Tick], None] | None = None,
        stop_when: Callable[[], bool] | None = None,
    ) -> TeleopSummary:
        """Tick until success / failure / the env's time limit / ``max_seconds`` / the end of
        a finite source plus ``tail_seconds`` (objects settle) / ``stop_when()`` (asked after
        every tick)."""
        start_wall = time.perf_counter()
        finished_at: float | None = None
        resets = self.resets
        success = False
        while True:
            if self.paced:
                target = self._t0 + self.ticks * self.dt
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            tick = self.tick()
            if progress is not None:
                progress(tick)
            success = success or tick.state.success
            elapsed = self.ticks * self.dt
            if (tick.state.success and stop_on_success) or tick.state.failure:
                break
            if stop_when is not None and stop_when():
                break
            if tick.state.truncated or (max_seconds is not None and elapsed >= max_seconds):
                break
            if self.resets != resets:  # reset from a view or a listener: a new episode
                resets, finished_at = self.resets, None
            if self.source.finished:
                finished_at = elapsed if finished_at is None else finished_at
                if elapsed - finished_at >= tail_seconds:
                    break
        return self.summary(success, wall_s=time.perf_counter() - start_wall)

    def summary(self, success: bool, wall_s: float | None = None) -> TeleopSummary:
        """The episode so far, as the CLI reports it."""
        env = self.twin.env
        return TeleopSummary(
            task=env.task.name,
            embodiment=env.embodiment.name,
            success=bool(success),
            frames_received=self.frames_received,
            frames_rejected=self.validator.rejected,
            commands_applied=self.twin.commands_applied,
            duration_s=self.ticks * self.dt,
            latency_ms=_percentiles(self.latencies_ms),
            rejected_by_reason=self.validator.rejected_by_reason,
            holds=dict(self.holds),
            operator={name: asdict(op.stats) for name, op in self.operator.effectors.items()},
            ticks=self.ticks,
            loop_rate_hz=self.ticks / wall_s if wall_s else None,
            guard_blocks=dict(getattr(self.twin, "guard_blocks", {})),
        )
