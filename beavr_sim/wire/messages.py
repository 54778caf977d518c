"""Typed wire messages between pipeline processes (msgspec Structs, msgpack on the wire).

Every message is a tagged Struct (field ``type`` on the wire), so a payload of the wrong kind
is rejected by name. :func:`decode` checks types *and* meaning (lengths, finite numbers, names
from a fixed set) and raises :class:`MessageError`; nothing here ever unpickles.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import msgspec
import numpy as np
from msgspec.structs import force_setattr

from beavr_sim.naming import check_name
from beavr_sim.wire.hand import N_JOINTS, RESOLUTIONS, SIDES, HandFrame

SESSION_COMMANDS = (
    "pause",
    "resume",
    "reset",
    "stop",
    # episode requests (``beavr_sim.teleop.episodes.session_command``) to the recording twin
    "record_toggle",
    "record_start",
    "record_stop",
    "record_discard",
    "record_quit",
    "estop",  # hardware mirroring: every device holds, latched
    "release",  # ... until released
)


class MessageError(ValueError):
    """A message that could not be decoded or failed validation."""


def _coerce(msg: msgspec.Struct, floats: tuple[str, ...], lists: tuple[str, ...]) -> None:
    """Let callers pass numpy scalars / arrays: store plain floats and lists (what msgpack
    encodes). Decoded messages already hold them, so this costs nothing on the receive side."""
    for name in floats:
        value = getattr(msg, name)
        if type(value) is not float:
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise TypeError(f"{name} must be a number, got {type(value).__name__}")
            force_setattr(msg, name, float(value))
    for name in lists:
        value = getattr(msg, name)
        if not isinstance(value, list):
            array = np.asarray(value, dtype=bool if name == "tracked" else np.float64)
            if array.ndim != 1 and not (name == "joints" and array.shape == (N_JOINTS, 3)):
                raise ValueError(f"{name} must be a flat list of numbers, got shape {array.shape}")
            force_setattr(msg, name, array.reshape(-1).tolist())


def _check_finite(name: str, values: Any) -> None:
    if isinstance(values, float):
        values = (values,)
    bad = [i for i, v in enumerate(values) if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{name} must be finite, got NaN/inf at index {bad[:5]}")


def _check_epoch(value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"epoch must be an integer >= 0, got {value!r}")


def _check_length(name: str, values: list, expected: int) -> None:
    if len(values) != expected:
        raise ValueError(f"{name} needs {expected} values, got {len(values)}")


class HandFrameMsg(msgspec.Struct, tag="hand_frame", kw_only=True, frozen=True):
    """A :class:`~beavr_sim.wire.hand.HandFrame` on the wire.

    ``joints``: 26 x 3 positions flattened row-major (metres, right-handed Z-up); untracked
    joints are sent as 0.0 so every number on the wire is finite.
    """

    side: str
    t_source: float
    t_receive: float
    joints: list[float]
    tracked: list[bool]
    pinch: bool = False
    resolution: str = "high"
    paused: bool = False

    def __post_init__(self) -> None:
        _coerce(self, ("t_source", "t_receive"), ("joints", "tracked"))
        check_name("side", self.side, SIDES)
        check_name("resolution", self.resolution, RESOLUTIONS)
        _check_finite("t_source", self.t_source)
        _check_finite("t_receive", self.t_receive)
        _check_length("joints", self.joints, 3 * N_JOINTS)
        _check_length("tracked", self.tracked, N_JOINTS)
        _check_finite("joints", self.joints)

    @classmethod
    def from_frame(cls, frame: HandFrame) -> HandFrameMsg:
        joints = np.where(frame.tracked[:, None], frame.joints, 0.0)
        return cls(
            side=frame.side,
            t_source=float(frame.t_source),
            t_receive=float(frame.t_receive),
            joints=joints.reshape(-1).tolist(),
            tracked=frame.tracked.tolist(),
            pinch=bool(frame.pinch),
            resolution=frame.resolution,
            paused=bool(frame.paused),
        )

    def to_frame(self) -> HandFrame:
        """The hand frame; untracked joints become NaN."""
        tracked = np.asarray(self.tracked, dtype=bool)
        joints = np.asarray(self.joints, dtype=np.float64).reshape(N_JOINTS, 3)
        joints[~tracked] = np.nan
        return HandFrame(
            side=self.side,
            t_source=self.t_source,
            t_receive=self.t_receive,
            joints=joints,
            tracked=tracked,
            pinch=self.pinch,
            resolution=self.resolution,
            paused=self.paused,
        )


class JointCommandMsg(msgspec.Struct, tag="joint_command", kw_only=True, frozen=True):
    """Joint targets for one effector: arm then hand joints, in the effector's action order.

    ``t_source``: ``t_source`` of the hand frame the targets came from; ``t_command``: when the
    operator produced them. ``hold``: keep the robot where it is (``positions`` are then the
    last targets, possibly empty); ``reason`` says why (e.g. ``"paused"``, ``"hand lost"``).
    ``epoch``: the twin's reset epoch the operator was homed in; the twin drops a command of
    an older epoch (computed from the robot's pose before a reset).
    """

    effector: str
    t_source: float
    t_command: float
    positions: list[float]
    hold: bool = False
    reason: str = ""
    epoch: int = 0
    #: Lockstep (virtual and paced clocks): the tick of the twin's state the command answers
    #: (-1: real time, the command applies when it arrives).
    tick: int = -1
    #: The operator's source has ended (the twin plays the tail, then ends the run).
    source_finished: bool = False

    def __post_init__(self) -> None:
        _coerce(self, ("t_source", "t_command"), ("positions",))
        if self.tick < -1:
            raise ValueError(f"tick must be >= -1 (-1: real time), got {self.tick}")
        _check_epoch(self.epoch)
        if not self.effector or "/" in self.effector:
            raise ValueError(
                f"effector must be a non-empty name without '/', got {self.effector!r}"
            )
        _check_finite("t_source", self.t_source)
        _check_finite("t_command", self.t_command)
        if not self.hold and not self.positions:
            raise ValueError("positions must be non-empty unless hold is set")
        _check_finite("positions", self.positions)


#: Numbers per fixture shape on the wire: MuJoCo geom type, size (3), pos (3), quat (4).
FIXTURE_GEOM_LENGTH = 11


class FixtureMsg(msgspec.Struct, kw_only=True, frozen=True):
    """A task fixture (a static obstacle placed at reset: Tape's box, Pour's cup) as the
    operator's IK needs it: its world pose (``pos``, ``quat`` w x y z) and its collision
    shapes, each ``[type, size x3, pos x3, quat x4]`` in the fixture's frame."""

    name: str
    pos: list[float]
    quat: list[float]
    geoms: list[list[float]]

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("a fixture needs a name")
        _check_length("pos", self.pos, 3)
        _check_length("quat", self.quat, 4)
        _check_finite("pos", self.pos)
        _check_finite("quat", self.quat)
        try:  # one array check rather than a Python loop per number (every state has them)
            geoms = np.array(self.geoms, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"fixture {self.name!r}: shapes of unequal length ({exc})") from None
        if geoms.ndim != 2 or geoms.shape[0] < 1 or geoms.shape[1] != FIXTURE_GEOM_LENGTH:
            raise ValueError(
                f"fixture {self.name!r} needs shapes of {FIXTURE_GEOM_LENGTH} numbers each, "
                f"got an array of shape {geoms.shape}"
            )
        if not np.isfinite(geoms).all():
            raise ValueError(f"fixture {self.name!r}: shapes must be finite")


class RobotStateMsg(msgspec.Struct, tag="robot_state", kw_only=True, frozen=True):
    """Twin state in action order, published every control tick (also the twin's heartbeat).

    ``epoch``: how many times the twin was reset; the operator re-homes from the first state
    of a newer epoch and never from an older one."""

    t: float
    positions: list[float]
    velocities: list[float]
    success: bool = False
    guard_blocked: bool = False
    #: The effectors the guard held this tick, and the action they hold (the operator
    #: continues from it); ``action`` may be empty when nothing was held.
    guard_blocked_effectors: list[str] = []
    action: list[float] = []
    epoch: int = 0
    #: The task's fixtures as this epoch's reset placed them (the operator's IK keeps the
    #: hands off them); every state carries them, so a conflated stream cannot lose them.
    fixtures: list[FixtureMsg] = []
    #: The operator holds (reason ``"paused"``): the browser view's Pause, its e-stop button
    #: or the mirror's latched emergency stop.
    paused: bool = False
    #: Lockstep (virtual and paced clocks): the tick this state asks the operator's commands
    #: for (-1: real time); ``done``: the episode ended, no tick follows.
    tick: int = -1
    done: bool = False
    #: The session's run this state belongs to (a recorded episode, a ``--repeat`` play;
    #: 0 before the first starts): on a new run the operator plays a trace from its start.
    run: int = 0

    def __post_init__(self) -> None:
        _coerce(self, ("t",), ("positions", "velocities", "action"))
        _check_epoch(self.epoch)
        if isinstance(self.run, bool) or not isinstance(self.run, int) or self.run < 0:
            raise ValueError(f"run must be an integer >= 0, got {self.run!r}")
        if self.tick < -1:
            raise ValueError(f"tick must be >= -1 (-1: real time), got {self.tick}")
        _check_finite("t", self.t)
        _check_length("velocities", self.velocities, len(self.positions))
        if self.action:
            _check_length("action", self.action, len(self.positions))
        elif self.guard_blocked_effectors:
            raise ValueError("guard_blocked_effectors needs the held action")
        _check_finite("positions", self.positions)
        _check_finite("velocities", self.velocities)
        _check_finite("action", self.action)


class SessionMsg(msgspec.Struct, tag="session", kw_only=True, frozen=True):
    """A session command from the UI.

    ``epoch`` (``"reset"``): the reset epoch the twin's states carry at least once it has
    done this reset (0: one more than now); the operator holds until such a state comes."""

    command: str
    t: float = 0.0
    epoch: int = 0

    def __post_init__(self) -> None:
        _coerce(self, ("t",), ())
        _check_epoch(self.epoch)
        check_name("session command", self.command, SESSION_COMMANDS)
        _check_finite("t", self.t)


#: Session events the operator recognises in the hands (operator -> twin).
#: ``estop``: both hands pinch at once (the mirror latches its e-stop); ``record``: a long
#: left pinch (a recording twin starts / stops an episode).
OPERATOR_EVENTS = ("estop", "record")


class OperatorEventMsg(msgspec.Struct, tag="operator_event", kw_only=True, frozen=True):
    """A session event the operator recognised (``event``, one of :data:`OPERATOR_EVENTS`) at
    ``t`` (the operator's clock); the twin acts on it (the e-stop latches its mirror, the record
    gesture toggles a recorded episode)."""

    event: str
    t: float = 0.0

    def __post_init__(self) -> None:
        _coerce(self, ("t",), ())
        check_name("operator event", self.event, OPERATOR_EVENTS)
        _check_finite("t", self.t)


class HandKeypointsMsg(msgspec.Struct, tag="hand_keypoints", kw_only=True, frozen=True):
    """The hands' newest frames as the operator observed them (operator -> twin, for the
    recorder's ``hand.keypoints``): per side at most one frame, the newest since the last
    message. Sent only when the recording wants keypoints. ``epoch``: as
    :class:`JointCommandMsg`'s; ``tick``: lockstep, the tick whose frames these are (the twin
    records tick k with tick k's keypoints; -1: real time, taken when it arrives)."""

    frames: list[HandFrameMsg] = []
    epoch: int = 0
    tick: int = -1

    def __post_init__(self) -> None:
        _check_epoch(self.epoch)
        if self.tick < -1:
            raise ValueError(f"tick must be >= -1 (-1: real time), got {self.tick}")
        sides = [f.side for f in self.frames]
        if len(set(sides)) != len(sides):
            raise ValueError(f"one frame per side at most, got sides {sides}")


#: The longest camera panel message carried (characters: a JPEG panel in base64, its status).
MAX_PANEL_CHARS = 8_000_000


class CameraPanelMsg(msgspec.Struct, tag="camera_panel", kw_only=True, frozen=True):
    """A streamed camera panel for the WebXR page (twin -> operator, whose process hosts the
    page's server): ``kind``, the page's message kind (``camera:NAME``), and ``message``, the
    page's message as JSON text."""

    kind: str
    message: str

    def __post_init__(self) -> None:
        if not self.kind.startswith("camera:") or len(self.kind) > 200:
            raise ValueError(f"a camera panel's kind is 'camera:NAME', got {self.kind[:200]!r}")
        if len(self.message) > MAX_PANEL_CHARS:
            raise ValueError(
                f"a camera panel message has at most {MAX_PANEL_CHARS} characters, got "
                f"{len(self.message)}"
            )


#: The longest twin scene carried (characters: the WebXR page's ``scene`` message as JSON, its
#: meshes in base64; a two-arm scene is ~0.3 MB).
MAX_SCENE_CHARS = 32_000_000
#: The most numbers a :class:`TwinPosesMsg` carries (12 per moving geom).
MAX_POSE_NUMBERS = 12 * 100_000


class TwinSceneMsg(msgspec.Struct, tag="twin_scene", kw_only=True, frozen=True):
    """The twin's scene as the WebXR page draws it (twin -> operator, whose process hosts the
    page's server; sent once): ``message``, the page's ``scene`` message as JSON text."""

    message: str

    def __post_init__(self) -> None:
        if len(self.message) > MAX_SCENE_CHARS:
            raise ValueError(
                f"a twin scene message has at most {MAX_SCENE_CHARS} characters, got "
                f"{len(self.message)}"
            )


class TwinPosesMsg(msgspec.Struct, tag="twin_poses", kw_only=True, frozen=True):
    """The twin's moving geoms for the WebXR page (twin -> operator, at the page's twin rate,
    newest only): ``t``, twin time (s); ``pose``, 12 numbers per moving geom of the scene
    (position, then ``R_world_geom`` row by row)."""

    t: float
    pose: list[float]

    def __post_init__(self) -> None:
        _coerce(self, ("t",), ("pose",))
        _check_finite("t", self.t)
        if len(self.pose) % 12 or len(self.pose) > MAX_POSE_NUMBERS:
            raise ValueError(
                f"pose must hold 12 numbers per geom, at most {MAX_POSE_NUMBERS}, got "
                f"{len(self.pose)}"
            )
        _check_finite("pose", self.pose)


Message = (
    HandFrameMsg
    | JointCommandMsg
    | RobotStateMsg
    | SessionMsg
    | OperatorEventMsg
    | HandKeypointsMsg
    | CameraPanelMsg
    | TwinSceneMsg
    | TwinPosesMsg
)
MESSAGE_TYPES: tuple[type, ...] = (
    HandFrameMsg,
    HandKeypointsMsg,
    JointCommandMsg,
    RobotStateMsg,
    SessionMsg,
    OperatorEventMsg,
    CameraPanelMsg,
    TwinSceneMsg,
    TwinPosesMsg,
)


@functools.cache
def _encoder() -> msgspec.msgpack.Encoder:
    return msgspec.msgpack.Encoder()


@functools.cache
def _decoder(expected_type: Any) -> msgspec.msgpack.Decoder:
    return msgspec.msgpack.Decoder(expected_type)


def encode(msg: Message) -> bytes:
    """msgpack bytes of a message."""
    if not isinstance(msg, MESSAGE_TYPES):
        raise MessageError(
            f"cannot encode {type(msg).__name__}; expected one of "
            f"{', '.join(t.__name__ for t in MESSAGE_TYPES)}"
        )
    return _encoder().encode(msg)


def decode[M](data: bytes | bytearray | memoryview, expected_type: type[M] | Any = Message) -> M:
    """Decode and validate ``data`` as ``expected_type`` (a message type or a union of them).

    Raises :class:`MessageError` naming what was wrong (bad msgpack, wrong message type, a
    missing field, a wrong length, a NaN, an unknown name).
    """
    name = getattr(expected_type, "__name__", None) or str(expected_type)
    try:
        return _decoder(expected_type).decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as err:
        raise MessageError(f"invalid {name} message: {err}") from None
