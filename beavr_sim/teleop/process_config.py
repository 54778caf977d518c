"""What the ``--multiprocess`` supervisor hands each process and what crosses between them.

The frozen configs (:class:`OperatorProcessConfig`, :class:`TwinProcessConfig`, their
sub-configs, :class:`Attachment`), passed whole to the spawned processes; the streams'
topics and timeouts; and the conversions of commands, keypoints and fixtures to and from
their wire messages (``wire/messages.py``). The processes: :mod:`beavr_sim.teleop.operator_process`,
:mod:`beavr_sim.teleop.twin_process`; the supervisor: :mod:`beavr_sim.teleop.processes`.
"""

from __future__ import annotations

import importlib
import logging
import math
import signal
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

import beavr_sim  # noqa: F401  (registers the envs the twin process makes)
from beavr_sim.envs.camera_pose import PlacedCamera
from beavr_sim.operator.obstacles import (
    Obstacle,
    ObstacleGeom,
    fixture_obstacles,
)
from beavr_sim.teleop.runs import RunPlan
from beavr_sim.teleop.stages import OperatorConfig
from beavr_sim.teleop.twin_camera_stream import (
    TwinCameraStream,
)
from beavr_sim.teleop.twin_page_stream import (
    TwinPageStream,
)
from beavr_sim.teleop.twin_rerun import TwinRerun
from beavr_sim.teleop.twin_runs import TwinRecording
from beavr_sim.wire.access import SessionToken
from beavr_sim.wire.messages import (
    FixtureMsg,
    HandFrameMsg,
    HandKeypointsMsg,
    JointCommandMsg,
)
from beavr_sim.wire.records import JointCommand

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


def leave_ctrl_c_to_the_session() -> None:
    """A worker ignores Ctrl-C: a terminal sends it to the whole process group, and the
    session (the parent) stops its processes in order (:meth:`MultiprocessSession.stop`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
