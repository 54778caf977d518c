"""``--multiprocess``: the operator (with the detector) and the twin as processes over ZeroMQ.

The same components as the single-process loop (``pipeline.py``), connected by the transport
(``transport.py``, ports from ``ports.py``):

    headset   --Quest app's PUSH strings-->  operator (detector + operator)
    operator  --commands (JointCommandMsg, topic = effector)-->  twin
    twin      --robot_state (RobotStateMsg, every tick: its heartbeat)-->  operator, supervisor
    supervisor --session (SessionMsg)-->  operator, twin
    twin      --camera panels (CameraPanelMsg, --camera-stream-hz, WebXR)-->  operator
    twin      --the page's twin (TwinSceneMsg once, TwinPosesMsg; WebXR, not headless)-->  operator

The pipeline is event-driven: nothing waits for a fixed clock on the way from a hand frame to
the actuators. The operator process owns the headset's sockets (``headset/``: parse, validate,
count) in its event loop, together with the robot state and session streams: each valid frame
is observed when it arrives and that hand's effectors are commanded at once (frames queued
behind a newer one are observed and counted as superseded; a side without frames for 1.5
control periods is commanded on the clock: its holds). The detector is not a process of its
own: on a small machine every process hop costs more than the detector's work (see
docs/benchmarks.md, 2026-12-02). The twin guards each command when it arrives, writes it to
its actuators' targets and hands it to the hardware mirror at once, while its physics steps
one control period at a time on its own real-time clock (the mirror also gets the targets
once per period when no command came: its heartbeat).

Each process creates its own ZMQ context, owns its sockets in its main thread, and runs on
the real clock. Latest-only streams are conflated. Publishers wait for their subscribers
(readiness handshake) before the session starts. Killing any one process leaves the others
alive: the twin keeps the last targets (the robot holds) when commands stop, the operator
holds when hand frames stop; the supervisor reports the death and stops on its own terms.
Processes are started with the ``spawn`` method (no state inherited from the parent) and
report their final counters to the supervisor as JSON over a pipe.

The per-frame path is the one of the single-process loop: both processes run its stages
(``stages.py``: the operator process an :class:`~beavr_sim.teleop.stages.OperatorStage`, the
twin process a :class:`~beavr_sim.teleop.stages.TwinStage`, whose hooks the mirror and
:class:`Attachment` s follow), each built from its frozen config (:class:`OperatorProcessConfig`,
:class:`TwinProcessConfig`) passed whole to the spawned process. The operator forwards the
both-hands-pinch e-stop to the twin (:class:`~beavr_sim.wire.messages.OperatorEventMsg`, which
latches the mirror); the twin's states carry whether the operator holds paused (the browser
view's Pause or e-stop, the mirror's latched e-stop). Mirrored, the twin brings the rig to the
episode's start pose before the episode (and after a reset) with the session's
:class:`~beavr_sim.teleop.mirroring.RigSync`, holding the start and dropping the operator's
commands meanwhile (lockstep: its states ask no tick); a rig that does not sync ends the
session (a ``done`` state; ``stopped_early`` in its report).

On the virtual and paced clocks (a trace) the processes run in lockstep: the twin publishes
the state of tick k, the operator answers it as one process's tick k (the frames up to k * dt,
every effector commanded), and the twin applies those commands and steps only once every
effector's arrived; paced, each tick's state is published at its wall deadline. A replay is
then the same episode as in one process, command for command.

The twin process plays the session's runs (a ``--repeat`` trace, recorded ``--episodes``:
:class:`~beavr_sim.teleop.twin_runs.TwinRuns`, with the single-process session's per-run
decisions) and records them (the recorder on its stage's ``after_step`` hook, fed the hands'
keypoints the operator sends on the command stream, :class:`~beavr_sim.wire.messages.HandKeypointsMsg`);
its states carry the run, and the operator plays a trace from its start on a new run. Live
recorded episodes start and stop on requests taken there: the supervisor's keyboard (session
commands ``record_*``), the browser view's buttons, the operator's record gesture (an
:class:`~beavr_sim.wire.messages.OperatorEventMsg`). Real cameras (``--camera``) are read there
next to the recorder and streamed from there (``--camera-stream-hz``:
:mod:`beavr_sim.teleop.twin_camera_stream`), its env places ``--camera-poses``' cameras, and
``--rerun`` logs from a hook of its stage (:mod:`beavr_sim.teleop.twin_rerun`). A single real-time run without recording
is ended by the supervisor (success, ``--max-seconds``). The WebXR page draws the twin from
its scene and poses sent by the twin process to the operator's page server
(:mod:`beavr_sim.teleop.twin_page_stream`).

Resets are numbered (epochs): the twin stamps every state with its epoch and drops commands
of an older one; the operator re-homes from the first state of a newer epoch only, and after
a reset request holds until that state comes (:class:`OperatorRehome`). The twin's physics
ticks on a :class:`~beavr_sim.teleop.pipeline.TickSchedule` (after a stall: no catch-up
burst, the skipped periods counted); an operator exception holds that side's effectors for a
command (reason ``"error"``), it never ends the process.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import math
import multiprocessing as mp
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import zmq

import beavr_sim  # noqa: F401  (registers the envs the twin process makes)
from beavr_sim.cameras.errors import CameraError
from beavr_sim.envs.beavr_env import DEFAULT_CONTROL_HZ
from beavr_sim.envs.camera_pose import PlacedCamera
from beavr_sim.hardware.device import MirrorError
from beavr_sim.hardware.mirror import Fixtures
from beavr_sim.headset.quest_io import HeadsetImagePublisher
from beavr_sim.headset.sources import QuestSource, TraceSource
from beavr_sim.headset.sources import WebXRSource as WebXRSourceType
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.operator.obstacles import (
    Obstacle,
    ObstacleGeom,
    fixture_obstacles,
)
from beavr_sim.operator.operator import Operator
from beavr_sim.robots import make_embodiment
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT
from beavr_sim.teleop.announce import announce_view, announce_webxr
from beavr_sim.teleop.episodes import (
    EpisodeControl,
    KeyboardControl,
    request_of,
    session_command,
)
from beavr_sim.teleop.images import HeadsetRenderer, ScenePose, headset_camera
from beavr_sim.teleop.mirroring import (
    MIRROR_SWITCH_INTERVAL_S,
    BrowserEstop,
    RigChoice,
    RigSync,
    connect_mirror,
    episode_fault,
    hardware_summary,
)
from beavr_sim.teleop.pipeline import (
    LatencyLog,
    TeleopSummary,
    ThreadedListener,
    TickSchedule,
    _percentiles,
    concrete_seed,
)
from beavr_sim.teleop.runs import RunPlan
from beavr_sim.teleop.stages import OperatorConfig, OperatorStage, TwinStage, count_hold
from beavr_sim.teleop.twin_camera_stream import (
    PANEL_TOPIC,
    PagePanels,
    TwinCameraStream,
    attach_camera_stream,
)
from beavr_sim.teleop.twin_page_stream import (
    POSES_TOPIC,
    SCENE_TOPIC,
    PageTwinRelay,
    TwinPageFeed,
    TwinPageStream,
)
from beavr_sim.teleop.twin_rerun import TwinRerun, attach_rerun
from beavr_sim.teleop.twin_runs import TwinRecording, TwinRuns, connect_real_cameras
from beavr_sim.traces.format import TraceReader
from beavr_sim.twin.twin import CommandOutcome, TwinInterface
from beavr_sim.viz.twin_view import TwinView, subtree_bodies
from beavr_sim.viz.view_access import ViewAccess
from beavr_sim.wire.access import SessionToken
from beavr_sim.wire.messages import (
    CameraPanelMsg,
    FixtureMsg,
    HandFrameMsg,
    HandKeypointsMsg,
    JointCommandMsg,
    OperatorEventMsg,
    RobotStateMsg,
    SessionMsg,
)
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.records import JointCommand, TwinState
from beavr_sim.wire.transport import Publisher, Subscriber

if TYPE_CHECKING:
    from beavr_sim.headset.webxr_server import WebXRConfig

log = logging.getLogger("beavr_sim.teleop.processes")

PROCESS_NAMES = ("operator", "twin")
#: Seconds without a message after which a stream's producer counts as dead.
LIVENESS_TIMEOUT_S = 0.5
HANDSHAKE_TIMEOUT_S = 10.0
#: Seconds a recording twin process gets to close its dataset and report when stopped.
STOP_RECORDING_S = 60.0
#: A side without a hand frame for this many control periods is commanded on the clock (its
#: holds). More than one: a 30 Hz headset's frames come a period apart, with jitter, and a
#: clock command just before each would repeat the last frame's.
CLOCK_COMMAND_AFTER = 1.5
#: ``--source webxr``: the operator waits on the page server this long at most at a time
#: (ms), then looks at its streams (robot state, session).
WEBXR_WAIT_MS = 5

#: The topic of the operator's session events on its command stream: no effector's name (never
#: with "/") is a prefix of it.
OPERATOR_EVENT_TOPIC = b"/operator_event"
#: The topic of the hands' keypoints (for the twin's recorder) on the command stream.
KEYPOINTS_TOPIC = b"/keypoints"


@dataclass(frozen=True)
class ViewConfig:
    """The twin process's browser view: where it is served and how often it updates."""

    host: str = "127.0.0.1"
    port: int = 8080
    rate_hz: float = 30.0
    show_collision: bool = False
    #: The session token for the controls that move the robot (None: everyone may press).
    token: SessionToken | None = None


@dataclass(frozen=True)
class HeadsetImagesConfig:
    """The twin process renders its headset camera and publishes the images to the Quest
    app (``--source quest`` without ``--headless``): at most ``rate_hz``, ``size`` (W, H)."""

    rate_hz: float = 10.0
    size: tuple[int, int] = (640, 360)


@dataclass(frozen=True)
class Attachment:
    """Something that attaches to the twin stage's hooks in the twin process, named by import
    path: ``target`` is ``"package.module:function"``, called there as
    ``function(twin_process, argument)`` with the :class:`TwinProcess`; it may return a
    callable run when the process ends (e.g. to write what it measured). The hooks a user
    has: the latency benchmark attaches its timing this way."""

    target: str
    argument: str = ""

    def __post_init__(self) -> None:
        module, _, name = self.target.partition(":")
        if not module or not name:
            raise ValueError(f"attachment target must be 'module:function', got {self.target!r}")

    def resolve(self) -> Callable:
        module, _, name = self.target.partition(":")
        return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class OperatorProcessConfig:
    """The operator process: its stage, its source (``"quest"``, ``"webxr"`` with the page
    server's config, hosted by this process, or ``"trace"`` with the trace's path) and whether it runs in lockstep with the twin (virtual and paced clocks)."""

    stage: OperatorConfig
    source: str
    trace: str | None = None
    lockstep: bool = False
    #: ``source="webxr"``: the page server this process hosts.
    webxr: WebXRConfig | None = None
    #: Send the hands' newest frames to the twin (its recorder's ``hand.keypoints``).
    keypoints: bool = False
    #: Forward the record gesture to the twin (it records: the gesture starts / stops).
    records: bool = False
    #: ``--camera-stream-hz`` with the WebXR page: the twin's panels to the page server.
    camera_panels: bool = False
    #: ``--source webxr`` without ``--headless``: the twin's scene and poses to the page server.
    page_twin: bool = False


@dataclass(frozen=True)
class TwinProcessConfig:
    """The twin process: the env (task, embodiment, control rate, LEAP variant; ``live``: no
    time limit), the episode's seed, the clock (``lockstep``: the twin steps only once the
    operator's commands for the tick arrived; ``paced``: lockstep ticks slept to the control
    rate), when a lockstep episode ends (as the single-process loop's ``run``), the mirrored
    rig (each episode, and a browser Reset, starts once the rig is at its start pose:
    :class:`~beavr_sim.teleop.mirroring.RigSync`), the browser view, the headset images and
    the attachments."""

    task: str
    embodiment: str
    control_hz: float
    seed: int | None = None
    live: bool = True
    leap_variant: str | None = None
    #: ``--camera-poses``: twin cameras at real cameras' poses (recorded, streamed, rendered).
    placed_cameras: tuple[PlacedCamera, ...] = ()
    lockstep: bool = False
    paced: bool = False
    stop_on_success: bool = True
    #: The session's runs (how many, the session's time limit) and ``--record`` (None: no
    #: recording): played by the twin (:class:`~beavr_sim.teleop.twin_runs.TwinRuns`).
    plan: RunPlan = field(default_factory=RunPlan)
    recording: TwinRecording | None = None
    #: ``--rerun``: the Rerun log, a hook of the twin stage (None: no log).
    rerun: TwinRerun | None = None
    #: Say each run's line on stderr.
    progress: bool = False
    mirror_hardware: bool = False
    hardware_config: str | None = None
    dry_run: bool = False
    #: Mirrored: how long (wall s) the rig may take to reach an episode's start pose (None:
    #: the rig file's); ``hardware_config="emulated"``: the faults its emulators inject.
    sync_timeout_s: float | None = None
    emulate_faults: str | None = None
    view: ViewConfig | None = None
    headset_images: HeadsetImagesConfig | None = None
    #: ``--camera-stream-hz``: the camera panels streamed from this process (None: off).
    camera_stream: TwinCameraStream | None = None
    #: ``--source webxr`` without ``--headless``: the twin drawn on the operator's page.
    page_twin: TwinPageStream | None = None
    attach: tuple[Attachment, ...] = ()

    @property
    def wants_keypoints(self) -> bool:
        """The operator sends the hands' frames: the recording stores keypoints, or the
        Rerun log draws the hands."""
        keypoints = self.recording is not None and self.recording.config.hand_keypoints
        return keypoints or self.rerun is not None

    @property
    def ends_runs(self) -> bool:
        """The twin ends the session's runs (lockstep, a recording, several runs); else, a
        single real-time run, the supervisor ends it (success, ``--max-seconds``)."""
        return self.lockstep or self.recording is not None or self.plan.several


def effector_slices(embodiment) -> dict[str, slice]:
    """Each effector's slice of the action vector (arm then hand joints, in effector order)."""
    slices, start = {}, 0
    for e in embodiment.effectors:
        slices[e.name] = slice(start, start + len(e.joints))
        start += len(e.joints)
    return slices


def command_to_wire(cmd: JointCommand, now: float, epoch: int, **lockstep) -> JointCommandMsg:
    """The operator's command as sent to the twin (a NaN source stamp, a hold's, as 0)."""
    return JointCommandMsg(
        effector=cmd.effector,
        t_source=cmd.t_source if math.isfinite(cmd.t_source) else 0.0,
        t_command=now,
        positions=np.asarray(cmd.positions, dtype=np.float64).tolist(),
        hold=cmd.hold,
        reason=cmd.reason,
        epoch=epoch,
        **lockstep,
    )


def command_from_wire(msg: JointCommandMsg, held: np.ndarray | None = None) -> JointCommand | None:
    """A command as the twin applies it: its positions, holding or not (an ``ik_infeasible``
    hold keeps the arm and moves the fingers: the twin applies it as one process does). A hold
    without positions keeps the last targets: None, or a hold at ``held`` where given (the
    lockstep tick, which applies every effector's command as one process does)."""
    if not msg.positions:
        if held is None:
            return None
        positions = held.copy()
    else:
        positions = np.asarray(msg.positions, dtype=np.float64)
    t_source = msg.t_source if msg.t_source > 0 else float("nan")
    return JointCommand(
        effector=msg.effector,
        positions=positions,
        t_source=t_source,
        t_receive=t_source,
        hold=msg.hold,
        reason=msg.reason,
    )


def keypoints_to_wire(frames, sides, epoch: int, tick: int = -1) -> HandKeypointsMsg:
    """The newest of ``frames`` (oldest first) of each of ``sides``, for the twin's recorder;
    a frame the wire refuses (it never should: they were validated) is left out, logged."""
    newest = {}
    for frame in frames:
        if frame.side in sides:
            newest[frame.side] = frame
    out = []
    for frame in newest.values():
        try:
            out.append(HandFrameMsg.from_frame(frame))
        except (TypeError, ValueError) as exc:
            log.warning("a %s hand frame not sent to the recorder: %s", frame.side, exc)
    return HandKeypointsMsg(frames=out, epoch=epoch, tick=tick)


def keypoints_from_wire(msg: HandKeypointsMsg) -> list:
    """:func:`keypoints_to_wire`'s frames back as hand frames (the recorder's input)."""
    return [frame.to_frame() for frame in msg.frames]


# ---------------------------------------------------------------------------- operator
def _leave_ctrl_c_to_the_session() -> None:
    """A worker ignores Ctrl-C: a terminal sends it to the whole process group, and the
    session (the parent) stops its processes in order (:meth:`MultiprocessSession.stop`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def operator_main(config: OperatorProcessConfig, transport: TransportConfig, conn) -> None:
    _leave_ctrl_c_to_the_session()
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


#: The twin's states carry the task's fixtures for this long after each reset (episode time,
#: s): the operator takes them from the first such state of the epoch, and the states after
#: stay small.
FIXTURES_FOR_S = 2.0


def fixtures_to_wire(env) -> list:
    """The env's fixtures as its reset placed them, for the robot state messages."""
    return [
        FixtureMsg(
            name=o.name,
            pos=list(o.pos),
            quat=list(o.quat),
            geoms=[[float(g.type), *g.size, *g.pos, *g.quat] for g in o.geoms],
        )
        for o in fixture_obstacles(env.model, env.data)
    ]


def obstacles_from_wire(fixtures) -> tuple:
    """:func:`fixtures_to_wire`'s messages back as the operator's obstacles."""
    return tuple(
        Obstacle(
            f.name,
            tuple(ObstacleGeom(int(g[0]), g[1:4], g[4:7], g[7:11]) for g in f.geoms),
            tuple(f.pos),
            tuple(f.quat),
        )
        for f in fixtures
    )


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


# ---------------------------------------------------------------------------- twin
#: Lockstep: seconds without the operator's commands for a tick before the twin asks again
#: (publishes the same state once more; a lost message never stalls the episode).
LOCKSTEP_ASK_AGAIN_S = 0.2


class TwinProcess:
    """What an :class:`Attachment` gets in the twin process: the config, the env, the twin
    stage (attach to its ``after_command`` / ``after_step`` hooks), the mirror (None when not
    mirroring), per effector the newest command's operator stamp and the moment the twin took
    it (:attr:`received`: ``(t_command, t_take)``, monotonic), and for the step just made
    (read them in an ``after_step`` hook) its commands (:attr:`tick_commands`: the lockstep
    tick's; real time: those applied since the step before) and its hand frames
    (:attr:`frames`, oldest first: sent by the operator only when the session records
    keypoints or logs to Rerun)."""

    def __init__(self, config: TwinProcessConfig, env, stage: TwinStage, mirror):
        self.config = config
        self.env = env
        self.stage = stage
        self.mirror = mirror
        self.received: dict[str, tuple[float, float]] = {}
        self.tick_commands: dict[str, JointCommand] = {}
        self.frames: list = []


def follow_with_mirror(stage: TwinStage, mirror, positions: np.ndarray) -> Callable[[], None]:
    """The hardware mirror follows the twin through its hooks: every command written (the
    guarded action, at once) and, after a step without one, the same targets (its heartbeat).
    ``positions``: the twin's joints at the start. Returns ``reset(positions)`` for a new
    episode."""
    twin = stage.twin
    last = {"positions": positions.copy(), "submitted": False}

    def after_command(outcome: CommandOutcome, commands) -> None:
        mirror.submit(twin.action.copy(), last["positions"], outcome.blocked)
        last["submitted"] = True

    def after_step(state: TwinState) -> None:
        if not last["submitted"]:  # no command this period: the same targets (heartbeat)
            mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
        last["submitted"] = False
        last["positions"] = state.positions

    def reset(q: np.ndarray) -> None:
        last["positions"] = np.asarray(q, dtype=np.float64).copy()

    after_command.__name__, after_step.__name__ = "mirror", "mirror"
    stage.after_command.insert(0, after_command)
    stage.after_step.insert(0, after_step)
    return reset


def make_twin_env(config: TwinProcessConfig):
    """The twin process's env (unwrapped): the task and embodiment at the control rate, no
    time limit when live, the LEAP variant and the placed cameras as one process's
    ``build_loop`` makes them."""
    kwargs: dict = {"control_hz": config.control_hz}
    if config.live:
        kwargs["max_episode_seconds"] = 1e9
    if config.leap_variant:
        kwargs["hand_variant"] = config.leap_variant
    if config.placed_cameras:
        kwargs["placed_cameras"] = config.placed_cameras
    return gym.make(f"beavr_sim/{config.task}-v0", embodiment=config.embodiment, **kwargs).unwrapped


def twin_main(config: TwinProcessConfig, transport: TransportConfig, conn) -> None:
    _leave_ctrl_c_to_the_session()
    context = zmq.Context()
    env = make_twin_env(config)
    twin = TwinInterface(env)
    stage = TwinStage(twin, latencies=LatencyLog())
    #: The seed of the episode (a reset from the supervisor or the browser replays it).
    episode_seed = concrete_seed(config.seed)
    positions = twin.reset(episode_seed)  # the twin's measured joints after its last step
    mirror = None
    sync = None
    closers: list[Callable[[], None]] = []
    mirror_reset = None
    if config.mirror_hardware:
        try:
            mirror, q_measured = connect_mirror(RigChoice.of(config), env, closers)
        except (MirrorError, ValueError, FileNotFoundError) as exc:
            for close in reversed(closers):
                close()
            conn.send_bytes(f"error: {exc}".encode())
            env.close()
            return
        twin.follow_speed_caps(mirror.speed_caps)
        twin.reset(episode_seed, q_measured)  # the mirror starts where the robot is
        sys.setswitchinterval(MIRROR_SWITCH_INTERVAL_S)  # see teleop/mirroring.py
        mirror.start(twin.action)
        # The episode's start; the devices catch up with it before the operator's commands
        # are taken (as one process's HardwareSync).
        sync = RigSync(mirror, config.sync_timeout_s or mirror.rig.mirror.sync_timeout_s)
        positions = twin.reset(episode_seed)
        mirror_reset = follow_with_mirror(stage, mirror, positions)
    try:  # the session's runs; recording: the dataset opened (a bad folder fails here)
        runs = TwinRuns(
            config.plan,
            env,
            stage,
            mirror,
            config.recording,
            frames=lambda: process.frames,
            stop_on_success=config.stop_on_success,
            progress=config.progress,
            seed=config.seed,
        )
        closers.append(runs.close)
        real = runs.real_cameras  # recording: the recorder's, streamed too
        streaming = config.camera_stream
        if streaming is not None and config.recording is None:
            real = connect_real_cameras(
                streaming.real_cameras, streaming.rig_file, int(round(env.control_hz))
            )
            if real is not None:
                closers.append(real.close)
    except (ValueError, OSError, CameraError) as exc:
        for close in reversed(closers):
            close()
        conn.send_bytes(f"error: {exc}".encode())
        env.close()
        return
    fixtures = fixtures_to_wire(env)
    subs = {
        e.name: Subscriber(
            context,
            transport.endpoint("commands", bind=False),
            e.name.encode(),
            JointCommandMsg,
            liveness_timeout_s=LIVENESS_TIMEOUT_S,
        )
        for e in env.embodiment.effectors
    }
    events = Subscriber(
        context,
        transport.endpoint("commands", bind=False),
        OPERATOR_EVENT_TOPIC,
        OperatorEventMsg,
        conflate=False,
    )
    keypoints = None
    if config.wants_keypoints:
        keypoints = Subscriber(
            context,
            transport.endpoint("commands", bind=False),
            KEYPOINTS_TOPIC,
            HandKeypointsMsg,
            conflate=False,
        )
    session = Subscriber(
        context, transport.endpoint("session", bind=False), b"session", SessionMsg, conflate=False
    )
    state_pub = Publisher(context, transport.endpoint("robot_state", bind=True))
    page_twin = None
    if config.page_twin is not None:  # the twin drawn on the operator's page
        page_twin = TwinPageFeed(env, config.page_twin)
        stage.after_step.append(page_twin)
    # operator + supervisor (+ the operator's page panels, its page's scene and poses)
    page = config.camera_stream is not None and config.camera_stream.page
    subscribers = 2 + int(page) + 2 * int(page_twin is not None)
    state_pub.wait_for_subscribers(subscribers, HANDSHAKE_TIMEOUT_S)
    if page_twin is not None:
        state_pub.send(SCENE_TOPIC, page_twin.scene)
    view = None
    if config.view is not None:
        joints = env.joints
        view = TwinView(
            env.render_model,
            host=config.view.host,
            port=config.view.port,
            task=env.task.name,
            embodiment=env.embodiment.name,
            effector_bodies=subtree_bodies(
                env.model, {n: joints.names[sl] for n, sl in joints.slices.items()}
            ),
            rate_hz=config.view.rate_hz,
            show_collision=config.view.show_collision,
            mirroring=mirror is not None,
            access=None if config.view.token is None else ViewAccess(config.view.token),
            episode_control=runs.control if config.recording is not None else None,
        )
        announce_view(view.url, config.view.token or SessionToken("-", False))
    browser_estop = None
    if view is not None and mirror is not None:
        browser_estop = BrowserEstop(view, mirror)
    publisher = None
    page_panels: PagePanels | None = None
    # the Quest app's camera panel shows the first real camera in place of the twin's images
    quest_panel = streaming is not None and streaming.quest and real is not None
    if config.headset_images is not None:
        images = config.headset_images
        publisher = HeadsetImagePublisher(context, transport, rate_hz=images.rate_hz)
        closers.append(publisher.close)
    if config.headset_images is not None and not quest_panel:
        renderer = HeadsetRenderer(
            publisher, env.render_model, headset_camera(env.embodiment), images.size
        )
        next_due = [0.0]

        def headset_pose(state: TwinState) -> ScenePose | None:
            now = time.monotonic()
            if now < next_due[0]:
                return None
            next_due[0] = now + 1.0 / images.rate_hz
            return ScenePose.of(env.data)

        # rendered and sent off the physics' thread; closed before the publisher
        headset = ThreadedListener(renderer, snapshot=headset_pose, name="headset_images")
        closers.append(headset.close)
        stage.after_step.append(headset)
    if streaming is not None:  # closed before the cameras, the view and the publisher
        page_panels = PagePanels() if streaming.page else None
        closers.append(
            attach_camera_stream(streaming, env, stage, real, view, publisher, page_panels)
        )
    process = TwinProcess(config, env, stage, mirror)
    if config.rerun is not None:
        closers.append(attach_rerun(process, config.rerun, real_time=not config.lockstep))
    finishers: list[Callable[[], None]] = []
    for attachment in config.attach:
        finish = attachment.resolve()(process, attachment.argument)
        if finish is not None:
            finishers.append(finish)
    poller = zmq.Poller()
    for sub in (*subs.values(), session, events, *([keypoints] if keypoints else [])):
        poller.register(sub.socket, zmq.POLLIN)
    conn.send_bytes(b"ready")
    blocked: set[str] = set()  # effectors the guard blocked since the last view update
    success = False
    details: dict = {}
    dt = 1.0 / env.control_hz
    # Real time: the physics steps on its own clock, one control period at a time; commands
    # are guarded and written to the actuators (and handed to the mirror) when they arrive,
    # in between. A stall moves the grid on (no catch-up steps). Paced lockstep: each tick's
    # state is published at its deadline.
    schedule = TickSchedule(dt)
    schedule.restart(time.monotonic() + dt)
    epoch = 0  # resets done: stamped on every state; commands of an older epoch are dropped
    stale: dict[str, int] = {}
    command_poller = zmq.Poller()
    for sub in subs.values():
        command_poller.register(sub.socket, zmq.POLLIN)
    slices = twin.slices
    # Lockstep: the tick whose commands (and keypoints) the twin waits for, those arrived,
    # the episode's end.
    tick = 0
    pending: dict[str, JointCommandMsg] = {}
    pending_keypoints: HandKeypointsMsg | None = None
    # Real time: the hand frames and commands taken since the last step (the next step's).
    pending_frames: list = []
    step_commands: dict[str, JointCommand] = {}
    done = False
    #: The session's runs: the run the states carry (a new one: the operator restarts a
    #: trace), whether the next episode start begins a new run, the source's end (real time).
    run = 0
    new_run_due = True
    source_finished_rt = False
    last_state: RobotStateMsg | None = None
    asked_at = -math.inf

    def state_message(st: TwinState | None, **lockstep) -> RobotStateMsg:
        paused = view is not None and (view.paused or view.estop_requested)
        paused = paused or (mirror is not None and mirror.estopped)
        if st is None:  # after a reset: the measured joints, at rest
            return RobotStateMsg(
                t=env.elapsed_seconds,
                positions=positions.tolist(),
                velocities=[0.0] * len(positions),
                success=success,
                epoch=epoch,
                fixtures=fixtures,
                paused=paused,
                run=run,
                **lockstep,
            )
        return RobotStateMsg(
            t=st.t,
            positions=st.positions.tolist(),
            velocities=st.velocities.tolist(),
            success=success,
            guard_blocked=st.guard_blocked,
            guard_blocked_effectors=list(st.guard_blocked_effectors),
            action=st.action.tolist() if st.guard_blocked_effectors else [],
            epoch=epoch,
            fixtures=fixtures if st.t < FIXTURES_FOR_S else [],
            paused=paused,
            run=run,
            **lockstep,
        )

    def publish(msg: RobotStateMsg) -> None:
        nonlocal last_state, asked_at
        last_state, asked_at = msg, time.monotonic()
        state_pub.send(b"state", msg)
        for panel in page_panels.take() if page_panels is not None else ():
            state_pub.send(PANEL_TOPIC, panel)
        poses = page_twin.take() if page_twin is not None else None
        if poses is not None:
            state_pub.send(POSES_TOPIC, poses)

    def take_keypoints() -> None:
        """The operator's keypoints: real time, this epoch's (for the next recorded step);
        lockstep, those of the tick the twin waits for."""
        nonlocal pending_keypoints
        msg = keypoints.recv(0.0) if keypoints is not None else None
        while msg is not None:
            if msg.epoch == epoch and not config.lockstep:
                pending_frames.extend(keypoints_from_wire(msg))
            elif msg.epoch == epoch and msg.tick == tick:
                pending_keypoints = msg
            msg = keypoints.recv(0.0)

    def take_commands() -> None:
        """Real time: every effector's newest command, guarded, written to the actuators'
        targets and handed to the hooks (the mirror) at once."""
        nonlocal source_finished_rt
        t_take = time.monotonic()
        applied = {}
        take_keypoints()
        for name, sub in subs.items():
            msg = sub.recv_latest(0.0)
            if msg is None:
                continue
            if msg.epoch < epoch:  # computed from the pose before a reset: hold
                stale[name] = stale.get(name, 0) + 1
                continue
            source_finished_rt = source_finished_rt or msg.source_finished
            cmd = command_from_wire(msg)
            if cmd is None:
                continue  # holding without targets: keep the last ones
            applied[name] = cmd
            process.received[name] = (msg.t_command, t_take)
        if applied:
            stage.command(applied)
            step_commands.update(applied)

    def take_tick_commands() -> None:
        """Lockstep: the commands (and keypoints) answering this tick's state."""
        take_keypoints()
        for name, sub in subs.items():
            msg = sub.recv_latest(0.0)
            if msg is None:
                continue
            if msg.epoch < epoch:
                stale[name] = stale.get(name, 0) + 1
            elif msg.epoch == epoch and msg.tick == tick:
                pending[name] = msg
                process.received[name] = (msg.t_command, time.monotonic())

    def tick_ready() -> bool:
        """Lockstep: every effector's command (and the keypoints) of this tick came."""
        return len(pending) == len(subs) and (keypoints is None or pending_keypoints is not None)

    def lockstep_step() -> TwinState:
        """One process's tick: every effector's command guarded and written, one step."""
        nonlocal tick, done, pending_keypoints
        cmds = {
            name: command_from_wire(msg, held=twin.action[slices[name]])
            for name, msg in sorted(pending.items())
        }
        source_finished = any(msg.source_finished for msg in pending.values())
        t_command = min(msg.t_command for msg in pending.values())
        pending.clear()
        # this tick's hand frames, for the hooks that record or log the step
        process.frames = keypoints_from_wire(pending_keypoints) if pending_keypoints else []
        pending_keypoints = None
        process.tick_commands = cmds
        st = stage.apply(cmds, entered_perf=0.0, latency=False)
        for name, cmd in cmds.items():
            if not (cmd.hold or name in st.guard_blocked_effectors) and cmd.t_source > 0:
                stage.latencies_ms.append((twin.applied_monotonic - t_command) * 1e3)
        tick += 1
        done = runs.stepped(st, source_finished) if runs.playing else False
        return st

    def between_substeps() -> None:
        # Commands that arrive while the physics steps are taken between its substeps (not
        # while the rig syncs: the twin holds the episode's start).
        if command_poller.poll(0) and not (sync is not None and sync.syncing):
            take_commands()

    def syncing_step() -> TwinState | None:
        """While the rig syncs: the operator's commands dropped (computed before the
        episode's start), the twin holds its start, one step a control period; None until
        the next period is due."""
        for name, sub in subs.items():
            if sub.recv_latest(0.0) is not None:
                held_for_sync[name] = held_for_sync.get(name, 0) + 1
        take_keypoints()  # (of frames before the episode's start: never recorded)
        pending_frames.clear()
        now = time.monotonic()
        if now < schedule.next:
            return None
        schedule.take(now)
        process.frames, process.tick_commands = [], {}
        return stage.step()

    def begin_run() -> None:
        """A run of the session starts here (after its reset and, mirrored, its sync)."""
        nonlocal run, new_run_due, source_finished_rt, success
        run, new_run_due, source_finished_rt, success = run + 1, False, False, False
        runs.begin(episode_seed)

    def start_episode() -> None:
        """After a reset, or a sync that completed: the episode starts (lockstep: tick 0;
        a new run where one is due, else the run goes on from a reset)."""
        nonlocal tick, done, success, pending_keypoints
        tick, done, success, pending_keypoints = 0, False, False, None
        pending.clear()
        if new_run_due:
            begin_run()
        if config.paced:
            schedule.restart()
            schedule.wait()
        publish(state_message(None, tick=0))

    def next_run() -> None:
        """The session's next run: the seeded start again (a new epoch); mirrored, once the
        rig is there."""
        nonlocal positions, epoch, fixtures, done, new_run_due, episode_seed
        done, new_run_due = False, True
        episode_seed = concrete_seed(runs.next_seed())
        positions = twin.reset(episode_seed)
        epoch += 1
        fixtures = fixtures_to_wire(env)
        if sync is not None:
            sync.begin(twin.action.copy(), Fixtures.of(env.data))
            mirror_reset(positions)
            publish(state_message(None))  # tick -1: the operator waits for the rig
        elif config.lockstep:
            start_episode()
        else:
            begin_run()

    def sync_s() -> float | None:
        return sync.last_sync_s if sync is not None else None

    held_for_sync: dict[str, int] = {}
    sync_fault = ""
    #: A live recording waits for a start request (the twin follows, nothing recorded).
    idle = runs.waits_for_start
    if sync is not None:  # its timeout runs from here, not from the processes' handshake
        sync.begin(twin.action.copy(), Fixtures.of(env.data))
    if not config.lockstep:
        env.between_substeps = between_substeps
        if sync is None and not idle:
            begin_run()
    elif sync is None or not sync.syncing:
        start_episode()
    else:
        publish(state_message(None))  # tick -1: the operator waits for the rig
    try:
        while True:
            if config.lockstep:
                poller.poll(math.ceil(LOCKSTEP_ASK_AGAIN_S * 250))
            else:
                remaining = schedule.next - time.monotonic()
                if remaining > 0:
                    poller.poll(math.ceil(remaining * 1000))
            msg = session.recv(0.0)
            if msg is not None and msg.command == "stop":
                break
            reset = msg is not None and msg.command == "reset"
            if reset or (view is not None and view.take_reset()):  # supervisor or browser
                positions = twin.reset(episode_seed)
                epoch = max(epoch + 1, msg.epoch if reset else 0)
                fixtures = fixtures_to_wire(env)
                if sync is not None:  # the devices catch up with the twin's start, guarded
                    sync.begin(twin.action.copy(), Fixtures.of(env.data))
                if mirror_reset is not None:
                    mirror_reset(positions)
                if config.lockstep and sync is None:
                    start_episode()
            if msg is not None and mirror is not None and msg.command == "estop":
                mirror.estop("keyboard")
            if msg is not None and mirror is not None and msg.command == "release":
                mirror.release()
            asked = request_of(msg.command) if msg is not None else None
            if asked is not None:
                runs.request(asked, "keyboard")
            event = events.recv(0.0)
            while event is not None:
                if event.event == "estop" and mirror is not None:
                    mirror.estop("headset gesture: both hands pinch")
                if event.event == "record":
                    runs.request("toggle", "headset gesture")
                event = events.recv(0.0)
            if sync_fault:  # the session ends: the supervisor stops on the done state
                if time.monotonic() - asked_at > LOCKSTEP_ASK_AGAIN_S:
                    publish(last_state)
                continue
            if sync is not None and sync.syncing:
                st = syncing_step()
                if st is None:
                    continue
                positions = st.positions
                if browser_estop is not None:
                    browser_estop(None)
                result = sync.poll()
                if result:
                    sync_fault = result
                    runs.sync_failed(result, sync.last_sync_s)
                    publish(state_message(st, done=True))
                elif result == "":  # in sync: the seeded start again, a new epoch
                    positions = twin.reset(episode_seed)
                    epoch += 1
                    fixtures = fixtures_to_wire(env)
                    mirror_reset(positions)
                    if config.lockstep:
                        start_episode()
                    elif new_run_due and not idle:
                        begin_run()
                else:
                    publish(state_message(st))
                continue
            if done:  # the session's runs are over: the supervisor stops on the done state
                if time.monotonic() - asked_at > LOCKSTEP_ASK_AGAIN_S:
                    publish(last_state)  # the end, again
                continue
            if config.lockstep:
                take_tick_commands()
                if not tick_ready():
                    if time.monotonic() - asked_at > LOCKSTEP_ASK_AGAIN_S:
                        publish(last_state)  # ask again: a lost message never stalls
                    continue
                st = lockstep_step()
            else:
                take_commands()
                now = time.monotonic()
                if now < schedule.next:
                    continue
                schedule.take(now)
                process.frames, process.tick_commands = list(pending_frames), dict(step_commands)
                pending_frames.clear()
                step_commands.clear()
                st = stage.step()
                ended = runs.stepped(st, source_finished_rt) if runs.playing else False
                done = ended and config.ends_runs
                if idle:  # a live recording between episodes
                    what = runs.idle_step()
                    if what == "start":
                        idle = False
                        next_run()
                        continue
                    done = what == "end"
            positions = st.positions
            if browser_estop is not None:
                browser_estop(None)
            success = success or st.success
            details = {k: v for k, v in st.info.items() if k.startswith("task/")}
            if done and runs.end(sync_s()):  # the run ended; the next one follows
                if runs.waits_for_start:  # ... on a start request: idle until then
                    idle, done, new_run_due = True, False, True
                else:
                    next_run()
                    continue
            if config.paced and not done:
                schedule.wait()
            if config.lockstep:
                publish(state_message(st, tick=tick, done=done))
            else:
                publish(state_message(st, done=done))
            if view is not None:
                if st.guard_blocked:  # shown at the next update even if it cleared since
                    blocked |= set(st.guard_blocked_effectors or view.guard.geoms)
                if view.due():
                    view.update(
                        env.data,
                        status=f"t = {st.t:5.1f} s · {'success' if success else 'running'}",
                        guard_blocked=blocked,
                        success=success,
                    )
                    blocked = set()
    finally:
        env.between_substeps = None
        if runs.playing:  # stopped by the supervisor: a run it ended, or one cut short
            runs.end(sync_s(), interrupted=config.recording is not None)
        hardware = {}
        if mirror is not None:
            mirror.close()
            hardware = hardware_summary(mirror)
        for finish in finishers:
            try:
                finish()
            except Exception as exc:
                log.error("twin attachment failed at the end: %r", exc)
        for close in reversed(closers):
            close()
        conn.send_bytes(
            json.dumps(
                {
                    "hardware": hardware,
                    "success": success,
                    "objects": {
                        n: o.pos(env.data).round(3).tolist()
                        for n, o in {**env.task.objects, **env.task.fixtures}.items()
                    },
                    "task_details": {
                        k: v for k, v in details.items() if isinstance(v, (bool, int, float, str))
                    },
                    "commands_applied": twin.commands_applied,
                    "guard_blocks": dict(twin.guard_blocks),
                    "step_limited": {
                        n: int(v) for n, v in getattr(twin, "step_limited", {}).items()
                    },
                    "stale_commands": stale,
                    "held_for_sync": held_for_sync,
                    "sync_s": sync.last_sync_s if sync is not None else None,
                    "stopped_early": sync_fault or runs.runs.stopped,
                    "runs": runs.report(),
                    "hardware_fault": sync_fault or (episode_fault(mirror) if mirror else ""),
                    "failed_devices": list(mirror.failed_devices) if mirror is not None else [],
                    "reset_epoch": epoch,
                    "overruns": schedule.overruns,
                    "missed_ticks": schedule.missed_ticks,
                    "latency_ms": stage.latencies_ms.percentiles(),
                    "hook_errors": dict(stage.hook_errors),
                    "duration_s": env.elapsed_seconds,
                    "ticks": tick if config.lockstep else int(round(env.elapsed_seconds / dt)),
                    "task": env.task.name,
                    "embodiment": env.embodiment.name,
                }
            ).encode()
        )
        if view is not None:
            view.close()
        state_pub.close()
        for s in (*subs.values(), session, events, *([keypoints] if keypoints else [])):
            s.close()
        env.close()
        context.term()


TARGETS = {"operator": operator_main, "twin": twin_main}


class MultiprocessSession:
    """Starts the three processes, watches them, stops them; see the module docstring."""

    def __init__(
        self,
        options,
        transport: TransportConfig | None = None,
        attach: tuple[Attachment, ...] = (),
    ):
        """``options``: a :class:`~beavr_sim.teleop.session.SessionOptions`; ``attach``: what
        attaches to the twin stage's hooks in the twin process (:class:`Attachment`)."""
        self.transport = transport or options.transport or TransportConfig()
        self.operator_config, self.twin_config = process_configs(options, attach)
        self.lockstep = self.twin_config.lockstep
        self.mirror_hardware = options.mirror_hardware
        self.ctx = mp.get_context("spawn")
        self.processes: dict[str, mp.process.BaseProcess] = {}
        self.pipes: dict[str, object] = {}
        self.results: dict[str, dict] = {}
        self.exits: dict[str, int | None] = {}
        #: Resets requested (each names the reset epoch the operator waits for).
        self.resets = 0
        #: Episode requests (keyboard, :meth:`request`) sent to the recording twin.
        self.episode_control = EpisodeControl()
        self.auto_start = bool(options.auto_start)

    @property
    def control_hz(self) -> float:
        return self.twin_config.control_hz

    def start(self) -> None:
        self.context = zmq.Context()
        self.session_pub = Publisher(self.context, self.transport.endpoint("session", bind=True))
        self.state_sub = Subscriber(
            self.context,
            self.transport.endpoint("robot_state", bind=False),
            b"state",
            RobotStateMsg,
            liveness_timeout_s=LIVENESS_TIMEOUT_S,
        )
        self._session_type = SessionMsg
        configs = {"operator": self.operator_config, "twin": self.twin_config}
        for name in ("twin", "operator"):
            parent, child = self.ctx.Pipe()
            proc = self.ctx.Process(
                target=TARGETS[name],
                args=(configs[name], self.transport, child),
                name=name,
                daemon=True,
            )
            proc.start()
            self.processes[name], self.pipes[name] = proc, parent
        for name, pipe in self.pipes.items():
            if not pipe.poll(60.0):
                self._abort_start()
                raise RuntimeError(f"{name} process did not become ready within 60 s")
            reply = pipe.recv_bytes()
            if reply != b"ready":
                self._abort_start(replied=name)
                raise MirrorError(reply.decode(errors="replace").removeprefix("error: "))
        self.session_pub.wait_for_subscribers(len(TARGETS), HANDSHAKE_TIMEOUT_S)
        self.send("resume")  # everyone is ready: the operator starts a trace now

    def send(self, command: str) -> None:
        """Send a session command; a ``"reset"`` names the epoch the twin will be in after it
        (at least: a reset from the twin's browser view counts too)."""
        epoch = 0
        if command == "reset":
            self.resets += 1
            epoch = self.resets
        self.session_pub.send(
            b"session", self._session_type(command=command, t=time.monotonic(), epoch=epoch)
        )

    def request(self, what: str, origin: str = "") -> None:
        """An episode request (``episodes.REQUESTS``) for the recording twin, from any
        thread; sent from :meth:`run`'s."""
        self.episode_control.request(what, origin)

    def dead(self) -> list[str]:
        return [n for n, p in self.processes.items() if not p.is_alive()]

    def _abort_start(self, replied: str = "") -> None:
        """A start that failed (a process answered an error, or one never became ready): no
        process has begun the session, so none has a report to give or a command to finish.
        The one that ``replied`` its error has closed what it opened and is exiting; the
        others are ended at once (a ``"stop"`` sent now may reach a process that has not
        subscribed yet, and would be waited for in vain)."""
        for name, proc in self.processes.items():
            if name != replied and proc.is_alive():
                proc.terminate()
        for name, proc in self.processes.items():
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
            self.exits[name] = proc.exitcode
        self.session_pub.close()
        self.state_sub.close()
        self.context.term()

    def stop(self) -> None:
        self.send("stop")
        for name, proc in self.processes.items():
            pipe = self.pipes[name]
            # a recording twin closes its dataset first: never killed while it writes
            patience = STOP_RECORDING_S if name == "twin" and self.twin_config.recording else 5.0
            if pipe.poll(patience if proc.is_alive() else 0.1):
                try:
                    self.results[name] = json.loads(pipe.recv_bytes())
                except (EOFError, ValueError):
                    pass
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
            self.exits[name] = proc.exitcode
        self.session_pub.close()
        self.state_sub.close()
        self.context.term()

    def run(
        self, max_seconds: float | None, stop_on_success: bool, interrupted=lambda: False
    ) -> TeleopSummary:
        """``interrupted()`` true (Ctrl-C / SIGTERM) ends the session in order, as the end
        of a run does."""
        self.start()
        requests: list[str] = []  # from the keyboard thread; sent from this one
        live_recording = self.twin_config.recording is not None and not self.auto_start
        interactive = sys.stdin is not None and sys.stdin.isatty()
        if interactive and (self.mirror_hardware or live_recording):
            actions = {}
            if self.mirror_hardware:
                actions = {
                    "e": ("emergency stop (every device holds)", lambda: requests.append("estop")),
                    "r": ("release the emergency stop", lambda: requests.append("release")),
                }
            keyboard = KeyboardControl(
                self.episode_control if live_recording else None, actions=actions
            )
            print(keyboard.help, file=sys.stderr)
        reported: set[str] = set()
        t0 = time.monotonic()
        success = False
        try:
            while True:
                state = self.state_sub.recv_latest(0.1)
                while requests:
                    self.send(requests.pop(0))
                for what in self.episode_control.take():
                    self.send(session_command(what))
                if state is not None:
                    success = success or state.success
                    if state.done:  # the twin ended the episode as one process's loop would,
                        break  # or its rig did not sync
                for name in self.dead():
                    if name not in reported:
                        reported.add(name)
                        log.error(
                            "%s process died (exit code %s); the others keep running and the "
                            "robot holds",
                            name,
                            self.processes[name].exitcode,
                        )
                elapsed = time.monotonic() - t0
                ends_runs = self.twin_config.ends_runs  # else a single real-time run
                if not ends_runs and (
                    (success and stop_on_success) or (max_seconds and elapsed >= max_seconds)
                ):
                    break
                if "twin" in reported or (ends_runs and reported) or interrupted():
                    break  # the twin's runs need both processes (lockstep: every tick)
        finally:
            self.stop()
        return self.summary(success, died=reported)

    def summary(self, success: bool = False, died=()) -> TeleopSummary:
        """The session's summary from the processes' final reports (after :meth:`stop`);
        ``died``: processes that died while it ran."""
        op, twin = self.results.get("operator", {}), self.results.get("twin", {})
        det = op.get("detector", {})
        summary = TeleopSummary(
            task=twin.get("task", self.twin_config.task),
            embodiment=twin.get("embodiment", self.twin_config.embodiment),
            success=bool(twin.get("success", success)),
            frames_received=det.get("frames_received", 0),
            frames_rejected=det.get("frames_rejected", 0),
            commands_applied=twin.get("commands_applied", 0),
            duration_s=twin.get("duration_s", 0.0),
            latency_ms=twin.get("latency_ms", _percentiles([])),
            rejected_by_reason=det.get("rejected_by_reason", {}),
            holds=merged_holds(op, twin),
            operator=op.get("operator", {}),
            processes={n: ("died" if n in died else "ok") for n in self.processes},
            guard_blocks=twin.get("guard_blocks", {}),
            hardware=twin.get("hardware", {}),
            ticks=twin.get("ticks", 0),
            listener_errors=twin.get("hook_errors", {}),
            overruns=op.get("overruns", 0) + twin.get("overruns", 0),
            missed_ticks=op.get("missed_ticks", 0) + twin.get("missed_ticks", 0),
            frames_superseded=sum(det.get("frames_superseded", {}).values())
            + sum(op.get("frames_superseded", {}).values()),
            failed_devices=list(twin.get("failed_devices", [])),
            stopped_early=twin.get("stopped_early", ""),
        )
        if "runs" in twin:  # every run, as one process counts them (the twin played them)
            summary.take_runs(twin["runs"])
        return summary


def merged_holds(operator: dict, twin: dict) -> dict[str, dict[str, int]]:
    """The summary's holds (effector -> reason -> ticks) from the processes' reports: the
    operator's hold reasons, and the twin's guard refusals, step clamps and commands dropped
    as computed before a reset."""
    holds = {name: dict(by_reason) for name, by_reason in operator.get("holds", {}).items()}
    for key, reason in (
        ("guard_blocks", "guard"),
        ("step_limited", "step_limit"),
        ("stale_commands", "stale_after_reset"),
        ("held_for_sync", "syncing"),
    ):
        for name, n in twin.get(key, {}).items():
            if n:
                count_hold(holds, name, reason, int(n))
    return holds


def process_configs(
    options, attach: tuple[Attachment, ...] = ()
) -> tuple[OperatorProcessConfig, TwinProcessConfig]:
    """The two processes' configs from a :class:`~beavr_sim.teleop.session.SessionOptions`:
    a trace's embodiment and seed where the options leave them open, the env's control rate,
    lockstep on the virtual and paced clocks."""
    embodiment, seed = options.embodiment, options.seed
    if options.source == "trace":
        meta = TraceReader(options.trace).metadata
        embodiment = embodiment or meta.embodiment or None
        seed = seed if seed is not None else meta.seed
    embodiment = embodiment or DEFAULT_EMBODIMENT
    sides = tuple(sorted({e.side for e in make_embodiment(embodiment).effectors}))
    lockstep = options.clock in ("virtual", "paced")
    stage = OperatorConfig(embodiment=embodiment, control_hz=DEFAULT_CONTROL_HZ, sides=sides)
    view = None
    if options.viser:
        view = ViewConfig(
            host=options.viser_host,
            port=options.viser_port,
            rate_hz=options.viser_rate_hz,
            show_collision=options.show_collision,
            token=options.session_token(options.viser_host),
        )
    recording = None
    if options.record is not None:
        recording = TwinRecording(
            root=str(options.record),
            repo_id=options.repo_id,
            config=options.recording,
            keep_faulty=options.keep_faulty_episodes,
            source=options.source,
            real_cameras=tuple(options.real_cameras),
            rig_file=options.camera_rig_file(),
            auto_start=bool(options.auto_start),
        )
    operator = OperatorProcessConfig(
        stage=stage,
        source=options.source,
        trace=str(options.trace) if options.trace is not None else None,
        lockstep=lockstep,
        webxr=options.webxr_config() if options.source == "webxr" else None,
    )
    twin = TwinProcessConfig(
        task=options.task,
        embodiment=embodiment,
        control_hz=stage.control_hz,
        seed=seed,
        live=options.source != "trace",
        leap_variant=options.leap_variant,
        placed_cameras=tuple(options.placed_cameras),
        lockstep=lockstep,
        paced=options.clock == "paced",
        stop_on_success=options.source == "trace",
        plan=RunPlan.of(options),
        recording=recording,
        rerun=(
            TwinRerun(
                str(options.rerun), options.rerun_image_hz, options.rerun_twin_hz, options.source
            )
            if options.rerun is not None
            else None
        ),
        progress=options.progress,
        mirror_hardware=options.mirror_hardware,
        hardware_config=options.hardware_config,
        dry_run=options.dry_run,
        sync_timeout_s=options.sync_timeout_s,
        emulate_faults=options.emulate_faults,
        view=view,
        headset_images=(
            HeadsetImagesConfig(options.headset_image_hz, tuple(options.headset_image_size))
            if options.source == "quest" and not options.headless
            else None
        ),
        camera_stream=(
            TwinCameraStream(
                options.camera_stream_hz,
                options.camera_view,
                placed=tuple(c.name for c in options.placed_cameras),
                quest=options.source == "quest" and not options.headless,
                page=options.source == "webxr",
                real_cameras=tuple(options.real_cameras),
                rig_file=options.camera_rig_file(),
            )
            if options.camera_stream_hz > 0
            else None
        ),
        page_twin=(
            TwinPageStream(options.webxr_config().twin_rate_hz)
            if options.source == "webxr" and not options.headless
            else None
        ),
        attach=tuple(attach),
    )
    return (
        dataclasses.replace(
            operator,
            keypoints=twin.wants_keypoints,
            records=twin.recording is not None,
            camera_panels=twin.camera_stream is not None and twin.camera_stream.page,
            page_twin=twin.page_twin is not None,
        ),
        twin,
    )


def run_multiprocess(options, interrupted=lambda: False) -> TeleopSummary:
    return MultiprocessSession(options).run(
        options.max_seconds, stop_on_success=options.source == "trace", interrupted=interrupted
    )
