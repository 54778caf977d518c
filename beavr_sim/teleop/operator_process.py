"""The operator process of ``--multiprocess``: :func:`operator_main`.

It owns the headset's sockets (or the WebXR page server, or the trace) and the operator
stage: each valid hand frame is observed when it arrives and that hand's effectors are
commanded at once over the commands stream; it takes the twin's states (re-homing after a
reset: :class:`OperatorRehome`; lockstep ticks on the virtual and paced clocks), forwards
the session's events (e-stop, record) and relays the twin's page messages to the page.
The layout as a whole: :mod:`beavr_sim.teleop.processes`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict

import numpy as np
import zmq

import beavr_sim  # noqa: F401  (registers the envs the twin process makes)
from beavr_sim.headset.sources import QuestSource, TraceSource
from beavr_sim.headset.sources import WebXRSource as WebXRSourceType
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.operator.operator import Operator
from beavr_sim.robots import make_embodiment
from beavr_sim.teleop.announce import announce_webxr
from beavr_sim.teleop.pipeline import (
    _percentiles,
)
from beavr_sim.teleop.process_config import (
    CLOCK_COMMAND_AFTER,
    HANDSHAKE_TIMEOUT_S,
    KEYPOINTS_TOPIC,
    LIVENESS_TIMEOUT_S,
    OPERATOR_EVENT_TOPIC,
    WEBXR_WAIT_MS,
    OperatorProcessConfig,
    command_to_wire,
    effector_slices,
    keypoints_to_wire,
    leave_ctrl_c_to_the_session,
    obstacles_from_wire,
)
from beavr_sim.teleop.stages import OperatorStage
from beavr_sim.teleop.twin_camera_stream import (
    PANEL_TOPIC,
)
from beavr_sim.teleop.twin_page_stream import (
    PageTwinRelay,
)
from beavr_sim.wire.messages import (
    CameraPanelMsg,
    OperatorEventMsg,
    RobotStateMsg,
    SessionMsg,
)
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.records import JointCommand
from beavr_sim.wire.transport import Publisher, Subscriber

log = logging.getLogger("beavr_sim.teleop.processes")


def operator_main(config: OperatorProcessConfig, transport: TransportConfig, conn) -> None:
    leave_ctrl_c_to_the_session()
    context = zmq.Context()
    embodiment = make_embodiment(config.stage.embodiment)
    control_hz = config.stage.control_hz
    dt = 1.0 / control_hz
    operator = Operator(embodiment, dt)
    # Each side's effectors are commanded when its hand frame arrives; a side without a
    # frame for CLOCK_COMMAND_AFTER control periods is commanded on the clock (holds:
    # tracking lost, paused, waiting), so the twin always hears from the operator.
    stage = OperatorStage(
        operator, control_hz, start=time.monotonic(), source_finished=lambda: source.finished
    )
    # The detector: the headset's sockets (or a trace) in this process's event loop; every
    # valid frame is observed (none is dropped unseen).
    validator = StreamValidator()
    if config.source == "trace":
        source = TraceSource(config.trace, real_time=not config.lockstep)
    elif config.source == "webxr":
        source = WebXRSourceType(config.webxr, validator)
        announce_webxr(source.url, config.webxr.token)
    else:
        source = QuestSource(context, transport, validator, latest_only=False)
    # A trace starts playing when the supervisor says every process is ready ("resume"), so
    # the operator anchors on its first frames as it would in one process.
    started = config.source != "trace"
    received = 0
    state = Subscriber(
        context,
        transport.endpoint("robot_state", bind=False),
        b"state",
        RobotStateMsg,
        liveness_timeout_s=LIVENESS_TIMEOUT_S,
    )
    session = Subscriber(
        context, transport.endpoint("session", bind=False), b"session", SessionMsg, conflate=False
    )
    panels = None
    bad_panels = 0  # camera panels that were no JSON object: dropped
    if config.camera_panels:  # the twin's camera panels, for the page server hosted here
        panels = Subscriber(
            context,
            transport.endpoint("robot_state", bind=False),
            PANEL_TOPIC,
            CameraPanelMsg,
            conflate=False,
            rcvhwm=8,
        )
    relay = None
    if config.page_twin:  # the twin drawn on the page served here
        relay = PageTwinRelay(context, transport, source.server, operator)
    commands = Publisher(context, transport.endpoint("commands", bind=True))
    # the twin's command subscribers, its operator-event subscriber (and its keypoints one)
    commands.wait_for_subscribers(
        len(embodiment.effectors) + 1 + int(config.keypoints), HANDSHAKE_TIMEOUT_S
    )
    # Start from the twin's measured joints.
    first = state.recv(HANDSHAKE_TIMEOUT_S)
    rehome = OperatorRehome(operator, effector_slices(embodiment))
    compute_ms: list[float] = []
    sides = list(config.stage.sides)
    #: Per side: frames observed but not commanded on their own (a newer one was queued).
    superseded = dict.fromkeys(sides, 0)
    frames_commanded = dict.fromkeys(sides, 0)
    clock_commands = dict.fromkeys(sides, 0)
    poller = zmq.Poller()
    for socket in (
        *source.sockets,
        state.socket,
        session.socket,
        *([panels.socket] if panels is not None else []),
        *(relay.sockets if relay is not None else ()),
    ):
        poller.register(socket, zmq.POLLIN)
    overruns = 0
    session_paused = False
    view_paused = False
    estop_events = 0
    record_events = 0
    answered: tuple[int, int] | None = None  # lockstep: (epoch, tick) last commanded
    run_seen: int | None = None  # the twin's run of the last state (a new one: the trace over)

    def set_paused() -> None:
        stage.set_paused(session_paused or view_paused)

    def send(out: dict[str, JointCommand], now: float, **lockstep) -> None:
        if relay is not None:
            relay.note(out)
        for name, cmd in out.items():
            commands.send(name.encode(), command_to_wire(cmd, now, rehome.epoch, **lockstep))

    def send_keypoints(frames: list, tick: int = -1) -> None:
        """The newest frame of each side among ``frames``, for the twin's recorder."""
        if config.keypoints:
            message = keypoints_to_wire(frames, sides, rehome.epoch, tick)
            commands.send(KEYPOINTS_TOPIC, message)

    def restart_on_new_run(msg: RobotStateMsg) -> None:
        """The twin started a new run (a recorded episode, a --repeat play): a trace plays
        from its start again (a browser Reset is a new epoch of the same run: not)."""
        nonlocal source, run_seen
        if run_seen is not None and msg.run > run_seen and config.source == "trace":
            source.close()
            source = TraceSource(config.trace, real_time=not config.lockstep)
            validator.reset()
        run_seen = msg.run if run_seen is None else max(run_seen, msg.run)

    def forward_events(now: float) -> None:
        """The both-hands pinch latches the twin's mirror (the e-stop gesture); a recording
        twin gets the record gestures (a long left pinch: start / stop an episode)."""
        nonlocal estop_events, record_events
        events = stage.take_events(record=config.records)
        if events.estop:
            estop_events += 1
            commands.send(OPERATOR_EVENT_TOPIC, OperatorEventMsg(event="estop", t=now))
        for _ in range(events.record):
            record_events += 1
            commands.send(OPERATOR_EVENT_TOPIC, OperatorEventMsg(event="record", t=now))

    def command_side(side: str, ok: bool) -> None:
        """Command ``side``'s effectors now, from what the operator has observed."""
        now = time.monotonic()
        finished = {"source_finished": True} if source.finished else {}
        hold = None
        if rehome.waiting:
            # Hold until the twin's state after the reset comes: re-homing to a state from
            # before it would drive the robot back where it was.
            rehome.warn_if_late(now)
            hold = "resetting"
        send(stage.command_side(side, now, ok, hold_reason=hold), now, **finished)

    def lockstep_tick(msg: RobotStateMsg) -> None:
        """Answer the twin's state of tick k as one process's tick k: the frames up to
        k * dt observed, every effector commanded at that time."""
        nonlocal received, answered
        if msg.tick < 0 or msg.done or answered == (msg.epoch, msg.tick) or rehome.waiting:
            return
        answered = (msg.epoch, msg.tick)
        t0 = time.monotonic()
        now = msg.tick * dt
        used = []
        for frame in source.poll(now):
            received += 1
            if source.validates or validator.check(frame) is None:
                used.append(frame)
        out = stage.command(now, stage.observe(used))
        send_keypoints(used, msg.tick)
        send(out, t0, tick=msg.tick, source_finished=source.finished)
        forward_events(t0)
        compute_ms.append((time.monotonic() - t0) * 1e3)

    def take_state(msg: RobotStateMsg) -> None:
        nonlocal view_paused
        if config.lockstep and answered == (msg.epoch, msg.tick) and not msg.done:
            return  # the twin asked again for a tick already answered
        restart_on_new_run(msg)
        stage.call("reset", rehome.on_state, msg)
        if msg.paused != view_paused:
            view_paused = msg.paused
            set_paused()

    if first is not None:  # homed on the twin's measured joints, then ready
        take_state(first)
    conn.send_bytes(b"ready")
    if first is not None and config.lockstep:
        lockstep_tick(first)

    receiver = getattr(source, "receiver", None)
    try:
        while True:
            early: list = []  # webxr: frames taken while waiting
            if config.lockstep:
                poller.poll(100)
            else:
                due = min(stage.last_command.values()) + CLOCK_COMMAND_AFTER * dt
                frame_due = source.next_due() if started else None
                if frame_due is not None:
                    due = min(due, frame_due)
                timeout_ms = max(0, math.ceil((due - time.monotonic()) * 1000))
                if isinstance(source, WebXRSourceType):
                    # frames come from the page server's thread, not a socket: wait on it,
                    # a short while at a time, and look at the streams in between
                    poller.poll(0)
                    early = source.wait(min(timeout_ms, WEBXR_WAIT_MS) / 1000)
                else:
                    poller.poll(timeout_ms)
            msg = session.recv(0.0)
            if msg is not None:
                if msg.command == "stop":
                    break
                if msg.command in ("pause", "resume"):
                    session_paused = msg.command == "pause"
                    set_paused()
                    started = started or msg.command == "resume"
                if msg.command == "reset":
                    rehome.expect(msg.epoch)
            panel = panels.recv(0.0) if panels is not None else None
            while panel is not None:  # to the page (never blocks: its server's thread sends)
                try:
                    message = json.loads(panel.message)
                except ValueError:
                    message = None
                if isinstance(message, dict):
                    source.server.publish(panel.kind, message)
                else:
                    bad_panels += 1  # dropped and counted, never raised in this loop
                panel = panels.recv(0.0)
            if relay is not None:
                relay.relay()
            latest = state.recv_latest(0.0)
            if latest is not None:
                take_state(latest)
                if config.lockstep:
                    lockstep_tick(latest)
            if config.lockstep:
                continue
            by_side: dict[str, list] = {}
            for frame in [*early, *source.poll(time.monotonic())] if started else ():
                received += 1
                if (source.validates or validator.check(frame) is None) and frame.side in sides:
                    by_side.setdefault(frame.side, []).append(frame)
            for side, frames in by_side.items():
                t0 = time.perf_counter()
                ok = True
                if not rehome.waiting:  # frames from before the reset are dropped
                    ok = stage.observe(frames)
                    superseded[side] += len(frames) - 1
                    frames_commanded[side] += 1
                command_side(side, ok)
                compute_ms.append((time.perf_counter() - t0) * 1e3)
            if by_side:
                send_keypoints([frames[-1] for frames in by_side.values()])
                forward_events(time.monotonic())
            now = time.monotonic()
            for side in sides:
                if now - stage.last_command[side] >= CLOCK_COMMAND_AFTER * dt:
                    if now - stage.last_command[side] > 1.1 * CLOCK_COMMAND_AFTER * dt:
                        overruns += 1
                    clock_commands[side] += 1
                    command_side(side, True)
    finally:
        conn.send_bytes(
            json.dumps(
                {
                    "compute_ms": _percentiles(compute_ms),
                    "operator": {n: asdict(op.stats) for n, op in operator.effectors.items()},
                    "holds": stage.holds,
                    "errors": stage.errors,
                    "reset_epoch": rehome.epoch,
                    "overruns": overruns,
                    "missed_ticks": 0,
                    "frames_superseded": superseded,
                    "frames_commanded": frames_commanded,
                    "clock_commands": clock_commands,
                    "estop_events": estop_events,
                    "record_events": record_events,
                    # the twin drawn on the page: poses handed to it, scenes dropped as bad
                    "page_twin": (
                        {"poses_sent": relay.poses_sent, "bad_scenes": relay.bad_scenes}
                        if relay is not None
                        else {}
                    ),
                    "bad_camera_panels": bad_panels,
                    "detector": {
                        "frames_received": received,
                        "frames_rejected": validator.rejected,
                        "rejected_by_reason": {
                            **validator.rejected_by_reason,
                            **source.refused_connections(),
                        },
                        # Quest source: payloads per stream, and frames replaced by a newer
                        # one in the same poll (0: every frame is passed on)
                        "quest_received": dict(receiver.received) if receiver else {},
                        "frames_superseded": dict(receiver.superseded) if receiver else {},
                    },
                }
            ).encode()
        )
        source.close()
        for s in (state, session, commands, *([panels] if panels is not None else [])):
            s.close()
        if relay is not None:
            relay.close()
        context.term()


class OperatorRehome:
    """The operator process's side of reset epochs.

    The twin stamps every robot state with its reset epoch (how many resets it has done).
    The operator re-homes from the first state of every newer epoch (a reset from the
    supervisor or the twin's own browser view) and ignores older ones. A reset request
    (:meth:`expect`) names the epoch the twin's states will carry at least after it; until
    one comes the operator holds (:attr:`waiting`), so it never re-homes to a state published
    before the reset, which the latest-only state stream can still hand it.
    """

    #: Seconds after a reset request without the twin's new state before a warning.
    WARN_AFTER_S = 1.0

    def __init__(self, operator, slices: dict[str, slice], clock=time.monotonic):
        self.operator = operator
        self.slices = slices
        self.clock = clock
        #: Epoch of the state the operator last re-homed from.
        self.epoch = 0
        self.homed = False  # no state yet: hold
        self.expected = 0
        self._since: float | None = None
        self._warned = False
        self._fixtures_epoch = -1  # the epoch whose fixtures the IK has

    @property
    def waiting(self) -> bool:
        """Holding: no state yet, or none since the reset requested last."""
        return not self.homed or self.epoch < self.expected

    def expect(self, epoch: int) -> None:
        """A reset was requested: hold until a state of ``epoch`` (0: the next epoch)."""
        self.expected = max(self.expected, epoch if epoch > 0 else self.epoch + 1)
        self._since, self._warned = self.clock(), False

    def on_state(self, msg) -> None:
        """Take a robot state: re-home on a newer epoch, continue from the guard's held
        action within the current one, ignore an older one."""
        if msg.epoch > self.epoch or not self.homed:
            self.operator.reset(np.asarray(msg.positions), self.slices)
            self._fixtures_epoch = -1
            self.epoch, self.homed = msg.epoch, True
            if not self.waiting:
                self._since = None
        if msg.epoch == self.epoch and msg.fixtures and self._fixtures_epoch != msg.epoch:
            self._fixtures_epoch = msg.epoch  # tried once per epoch
            try:
                self.operator.set_obstacles(obstacles_from_wire(msg.fixtures))
            except (ValueError, RuntimeError) as exc:  # the guard still keeps the robot off
                log.warning("fixtures of epoch %d not usable by the IK: %s", msg.epoch, exc)
        if msg.epoch == self.epoch and msg.guard_blocked_effectors:  # continue where held
            for name in msg.guard_blocked_effectors:
                if name in self.slices:
                    self.operator.resync(name, np.asarray(msg.action)[self.slices[name]])

    def warn_if_late(self, now: float) -> None:
        if self._since is not None and not self._warned and now - self._since > self.WARN_AFTER_S:
            self._warned = True
            log.warning(
                "no robot state after the reset (epoch %d) for %.1f s: holding until it comes",
                self.expected,
                now - self._since,
            )
