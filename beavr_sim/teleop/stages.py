"""The per-frame stages of a teleop session, written once for both runners.

Two stages with narrow typed interfaces, used by the single-process loop (``pipeline.py``,
direct calls) and by the two processes of ``--multiprocess`` (``processes.py``, the same calls
on either side of the ``wire/`` transport):

- :class:`OperatorStage`: hand frames + time -> a :class:`~beavr_sim.wire.records.JointCommand`
  per effector. It observes frames (an operator exception is counted and the tick holds,
  reason ``"error"``), commands every effector (a tick of the virtual clock) or one side's (a
  hand frame's arrival; the time a command stands for is at least
  :data:`MIN_COMMAND_DT_S` and at most a control period), counts holds per effector and reason,
  and hands out the session events the operator recognised (:class:`SessionEvents`: the
  both-hands-pinch e-stop, the record gesture).
- :class:`TwinStage`: commands -> :class:`~beavr_sim.twin.twin.CommandOutcome` (guarded and
  written to the twin's actuator targets at once), :meth:`TwinStage.step` ->
  :class:`~beavr_sim.wire.records.TwinState`. What watches or follows the twin attaches to its
  named hooks, dm_control-composer style: ``after_command(outcome, commands)`` after every
  command written between steps (the hardware mirror, a latency timer), ``after_step(state)``
  after every physics step (the mirror's heartbeat, the views, a state publisher),
  ``after_reset(q)`` after :meth:`TwinStage.reset` started a new episode at joints ``q`` (the
  mirror's follower, :class:`~beavr_sim.teleop.mirroring.MirrorFollower`). Latency is
  counted once per accepted command.

Neither stage raises on the per-tick path: an exception from the operator is a counted hold,
an exception from a hook is counted per hook (:attr:`TwinStage.hook_errors`) and logged,
rate-limited; :class:`StopTeleop` alone passes through (a hook ending the run on purpose).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from beavr_sim.operator.operator import Operator
from beavr_sim.twin.twin import CommandOutcome, TwinInterface
from beavr_sim.wire.records import JointCommand, TwinState

log = logging.getLogger(__name__)

#: The shortest time (s) one command stands for in real time (a command per hand frame): two
#: frames bunched by scheduling move the arm's IK target no faster than its speed cap allows.
MIN_COMMAND_DT_S = 0.002

#: ``after_command`` hooks: called with the outcome and the commands (effector -> command).
CommandHook = Callable[[CommandOutcome, Mapping[str, JointCommand]], None]
#: ``after_step`` hooks: called with the state after the step.
StepHook = Callable[[TwinState], None]
#: ``after_reset`` hooks: called with the twin's joints (action order) at the episode's start.
ResetHook = Callable[[np.ndarray], None]


class LatencySink(Protocol):
    """Where a stage's latencies (ms) go: a list, or the runners' bounded log."""

    def append(self, value: float, /) -> None: ...

    def __len__(self) -> int: ...


class StopTeleop(Exception):
    """Raise it from a tick listener, a hook (or ``progress``) to end the run on purpose; any
    other exception a listener raises is counted and logged, and the loop goes on."""


def should_log(count: int) -> bool:
    """Whether the ``count``-th repeat of one problem is worth a log line (1st, 10th, 100th,
    then every 1000th): a failure every tick must not flood the log at the control rate."""
    return count in (1, 10, 100) or count % 1000 == 0


def operator_call(errors: dict[str, int], what: str, fn: Callable, *args) -> tuple[bool, object]:
    """``(True, fn(*args))``, or ``(False, None)`` when it raises, counted in ``errors[what]``
    and logged (rate-limited): an operator error holds the robot for a tick, it never ends the
    session (either runner)."""
    try:
        return True, fn(*args)
    except Exception as exc:
        n = errors[what] = errors.get(what, 0) + 1
        if should_log(n):
            log.error(
                "operator.%s failed (%d so far): %r; every effector holds this tick",
                what,
                n,
                exc,
                exc_info=n == 1,
            )
        return False, None


def count_hold(holds: dict[str, dict[str, int]], effector: str, reason: str, n: int = 1) -> None:
    """Add ``n`` ticks of ``effector`` holding for ``reason`` to ``holds``
    (effector -> reason -> ticks, the summary's shape)."""
    by_reason = holds.setdefault(effector, {})
    by_reason[reason or "hold"] = by_reason.get(reason or "hold", 0) + n


def listener_name(listener: object) -> str:
    """How a listener is named in the summary and the log: a function's name, else its class."""
    name = getattr(listener, "__name__", None)
    return name if isinstance(name, str) and name else type(listener).__name__


@dataclass(frozen=True)
class SessionEvents:
    """What the operator recognised since it was last asked: the both-hands-pinch emergency
    stop and the record gesture (a long left pinch; how many)."""

    estop: bool = False
    record: int = 0


@dataclass(frozen=True)
class OperatorConfig:
    """What the operator stage of a session is built from (passed whole to a spawned process).

    ``embodiment``: the robot's name; ``control_hz``: the env's control rate (a command stands
    for at most one period of it); ``sides``: the hands that drive the embodiment."""

    embodiment: str
    control_hz: float
    sides: tuple[str, ...]

    def __post_init__(self) -> None:
        if not (self.control_hz > 0 and math.isfinite(self.control_hz)):
            raise ValueError(f"control_hz must be positive and finite, got {self.control_hz}")


class OperatorStage:
    """Hand frames + time -> commands per effector; see the module docstring.

    ``hold_positions(effector)``: where an effector holds when the operator fails (the twin's
    last target, in one process); None: an empty position vector, which the twin reads as
    "keep the last targets" (the operator process, which does not see the twin's action).
    ``start``: the time of each side's previous command before the first one (-inf: the first
    command stands for a whole control period). ``source_finished()``: whether the hand source
    will send no more frames (a trace at its end), told to the operator before each command
    (its wait for frames then holds as ``"source_ended"``, not ``"tracking_lost"``); None: a
    live source, never finished."""

    def __init__(
        self,
        operator: Operator,
        control_hz: float,
        *,
        hold_positions: Callable[[str], np.ndarray] | None = None,
        start: float = -math.inf,
        source_finished: Callable[[], bool] | None = None,
    ):
        self.operator = operator
        self.source_finished = source_finished
        self.dt = 1.0 / control_hz
        self.hold_positions = hold_positions
        #: Ticks each effector held, by reason (effector -> reason -> ticks).
        self.holds: dict[str, dict[str, int]] = {}
        #: Exceptions raised by the operator (each one a tick of holds), per call.
        self.errors: dict[str, int] = {}
        self.sides = tuple(sorted({op.side for op in operator.effectors.values()}))
        self.side_effectors = {
            side: tuple(n for n, op in operator.effectors.items() if op.side == side)
            for side in self.sides
        }
        #: When each side was last commanded.
        self.last_command = dict.fromkeys(self.sides, start)

    def call(self, what: str, fn: Callable, *args) -> tuple[bool, object]:
        """``fn(*args)`` with an exception counted as the operator's (see :func:`operator_call`)."""
        return operator_call(self.errors, what, fn, *args)

    def observe(self, frames: Iterable) -> bool:
        """Observe every frame; False when the operator raised on one (this tick holds)."""
        ok = True
        for frame in frames:
            ok = self.call("observe", self.operator.observe, frame)[0] and ok
        return ok

    def command(self, now: float, ok: bool = True) -> dict[str, JointCommand]:
        """Every effector's command at ``now`` (a tick of the virtual clock); with ``ok``
        False (the operator failed this tick) every effector holds, reason ``"error"``."""
        if ok:
            self.note_source_end()
            ok, out = self.call("command", self.operator.command, now)
        if not ok:
            out = self.hold("error", self.operator.effectors)
        self.count_holds(out)
        return out

    def command_side(
        self, side: str, now: float, ok: bool = True, hold_reason: str | None = None
    ) -> dict[str, JointCommand]:
        """``side``'s effectors' commands at ``now`` (a hand frame arrived, or the side's
        clock command); the time since the side's previous command is what the command stands
        for. ``hold_reason``: the side holds for that reason instead (e.g. ``"resetting"``)."""
        dt = min(max(now - self.last_command[side], MIN_COMMAND_DT_S), self.dt)
        self.last_command[side] = now
        names = self.side_effectors[side]
        if hold_reason is not None:
            out = self.hold(hold_reason, names)
        else:
            if ok:
                self.note_source_end()
                ok, out = self.call("command", self.operator.command, now, side, dt)
            if not ok:
                out = self.hold("error", names)
        self.count_holds(out)
        return out

    def note_source_end(self) -> None:
        """Tell the operator whether the source has ended (see the class docstring)."""
        if self.source_finished is not None:
            self.call("set_source_ended", self._set_source_ended)

    def _set_source_ended(self) -> None:
        self.operator.set_source_ended(bool(self.source_finished()))

    def hold(self, reason: str, names: Iterable[str]) -> dict[str, JointCommand]:
        """A hold of these effectors (not counted: :meth:`count_holds` does that)."""
        nan = float("nan")
        empty = np.zeros(0)
        return {
            name: JointCommand(
                effector=name,
                positions=(self.hold_positions(name) if self.hold_positions is not None else empty),
                t_source=nan,
                t_receive=nan,
                hold=True,
                reason=reason,
            )
            for name in names
        }

    def count_holds(self, commands: Mapping[str, JointCommand]) -> None:
        for name, cmd in commands.items():
            if cmd.hold:
                count_hold(self.holds, name, cmd.reason)

    def guard_refused(self, name: str, target: np.ndarray) -> None:
        """The twin's guard refused ``name``'s command: count it, and continue from where the
        twin holds it (``target``)."""
        count_hold(self.holds, name, "guard")
        self.call("resync", self.operator.resync, name, target)

    def set_paused(self, paused: bool) -> None:
        self.operator.set_paused(paused)

    def take_events(self, *, record: bool = True) -> SessionEvents:
        """The session events recognised since the last call (``record``: take the record
        gestures too; a session that does not record leaves them)."""
        estop = bool(self.operator.take_gestures("estop"))
        n_record = len(self.operator.take_gestures("record")) if record else 0
        return SessionEvents(estop=estop, record=n_record)


class TwinStage:
    """Commands -> :class:`CommandOutcome`; :meth:`step` -> :class:`TwinState`; named hooks.

    :attr:`latencies_ms`: per accepted command, from its hand frame's entry into the pipeline
    (``t_receive``, monotonic; on the virtual clock the tick's poll, ``entered_perf`` of
    :meth:`apply`) to the moment the guarded command was written to the actuators."""

    def __init__(
        self,
        twin: TwinInterface,
        *,
        hook_errors: dict[str, int] | None = None,
        latencies: LatencySink | None = None,
    ):
        self.twin = twin
        #: ``after_command(outcome, commands)``: after each command written between steps.
        self.after_command: list[CommandHook] = []
        #: ``after_step(state)``: after each physics step.
        self.after_step: list[StepHook] = []
        #: ``after_reset(q)``: after each :meth:`reset` (``q``: the twin's joints there).
        self.after_reset: list[ResetHook] = []
        #: Where the latencies go (given: e.g. the runners' bounded ``LatencyLog``).
        self.latencies_ms: LatencySink = [] if latencies is None else latencies
        #: Exceptions raised by hooks, per hook name (the stage went on; given: counted there).
        self.hook_errors: dict[str, int] = {} if hook_errors is None else hook_errors

    @property
    def action(self) -> np.ndarray:
        return self.twin.action

    def reset(self, seed: int | None = None, robot_qpos: np.ndarray | None = None) -> np.ndarray:
        """A new episode: the twin reset (:meth:`TwinInterface.reset`: the robot at
        ``robot_qpos`` or home); then the ``after_reset`` hooks. Returns the twin's joints."""
        q = self.twin.reset(seed, robot_qpos)
        for hook in self.after_reset:
            self._call_hook(hook, np.array(q, dtype=np.float64))
        return q

    def command(
        self, commands: Mapping[str, JointCommand], *, latency: bool = True
    ) -> CommandOutcome:
        """Guard ``commands`` and write them to the actuator targets now (between steps);
        count the latency of each accepted one from its ``t_receive`` (monotonic; unless
        ``latency`` is False); call the ``after_command`` hooks."""
        outcome = self.twin.command(commands)
        for name in outcome.accepted if latency else ():
            t_receive = commands[name].t_receive
            if math.isfinite(t_receive):
                self.latencies_ms.append((self.twin.applied_monotonic - t_receive) * 1e3)
        for hook in self.after_command:
            self._call_hook(hook, outcome, commands)
        return outcome

    def apply(
        self, commands: Mapping[str, JointCommand], *, entered_perf: float, latency: bool = True
    ) -> TwinState:
        """One tick of the virtual clock: the commands guarded and written, one physics
        period, the ``after_step`` hooks. Latency (unless ``latency`` is False) of each
        command neither holding nor refused, from ``entered_perf`` (``time.perf_counter``)."""
        state = self.twin.apply(commands)
        if latency:
            blocked = state.guard_blocked_effectors
            for cmd in commands.values():
                if not (cmd.hold or cmd.effector in blocked):
                    self.latencies_ms.append((self.twin.applied_perf - entered_perf) * 1e3)
        for hook in self.after_step:
            self._call_hook(hook, state)
        return state

    def step(self) -> TwinState:
        """One physics period towards the newest targets; then the ``after_step`` hooks."""
        state = self.twin.step()
        for hook in self.after_step:
            self._call_hook(hook, state)
        return state

    def _call_hook(self, hook: Callable, *args) -> None:
        try:
            hook(*args)
        except StopTeleop:
            raise
        except Exception as exc:
            name = listener_name(hook)
            n = self.hook_errors[name] = self.hook_errors.get(name, 0) + 1
            if should_log(n):
                log.warning(
                    "twin hook %s failed (%d so far): %r; teleoperation goes on",
                    name,
                    n,
                    exc,
                    exc_info=n == 1,
                )
