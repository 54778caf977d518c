"""The WebXR page's wire format (version 1): JSON text messages over one WebSocket.

Page -> detector, once per XR frame (``docs/formats.md`` has the full table)::

    {"v": 1, "type": "hands", "seq": 17, "t": 1718000000123.4, "paused": false,
     "hands": {"right": {"p": [75], "q": [100], "r": [25], "pinch": false}, "left": null}}

``t``: the XR frame's time on the page's clock, ms since the Unix epoch
(``performance.timeOrigin + XRFrame time``). Per hand, the 25 WebXR joints in the
specification's order (:data:`WEBXR_JOINTS`): ``p`` positions (x, y, z, metres, in the
session's ``local-floor`` reference space: right-handed, Y up, -Z forward), ``q`` orientations
(x, y, z, w), ``r`` radii (metres); a joint without a pose is ``null`` in all three (JSON has
no NaN). ``pinch``: thumb tip to ring tip closed (the page's hysteresis), ``paused``: the page's
Pause button. A hand that is absent or ``null`` is not tracked in that frame.

``hello`` (``{"v": 1, "type": "hello", "agent": ..., "page": ...}``) and ``session``
(``{"v": 1, "type": "session", "state": "started" | "ended", "mode": ...}``) are
informational.

Parsing is strict (unknown fields, wrong types or lengths, numbers JSON cannot hold (NaN,
1e999), out-of-room positions, non-unit quaternions are errors) and raises :class:`WebXRProtocolError` whose ``reason`` is one
of :data:`REASONS`; it never evaluates anything (JSON only, never pickle).
"""

from __future__ import annotations

import math
from typing import Literal

import msgspec
import numpy as np

from beavr_sim.headset.layouts import LAYOUTS, to_hand_frame
from beavr_sim.naming import check_name
from beavr_sim.wire.hand import SIDES, HandFrame

PROTOCOL_VERSION = 1
#: Longest message accepted (two hands of 200 numbers each fit in about 8 KiB).
MAX_MESSAGE_BYTES = 64 * 1024
#: Largest accepted |position| in metres: a tracking space is a room.
MAX_ABS_COORD_M = 10.0
#: Accepted joint radii (metres).
RADIUS_RANGE_M = (0.0, 0.1)
#: Quaternions may deviate this much from unit norm (the page rounds to 1e-5).
QUAT_NORM_TOLERANCE = 1e-2
N_WEBXR_JOINTS = 25
#: WebXR Hand Input joint names, in the specification's order (the ``webxr25`` layout).
WEBXR_JOINTS: tuple[str, ...] = LAYOUTS["webxr25"].joint_names

#: Every ``WebXRProtocolError.reason``.
REASONS = (
    "binary",
    "too_long",
    "not_json",
    "not_object",
    "unknown_version",
    "unknown_type",
    "schema",
    "bad_time",
    "unknown_hand",
    "wrong_shape",
    "partial_joint",
    "too_far",
    "bad_orientation",
    "bad_radius",
)

MESSAGE_TYPES = ("hands", "hello", "session")


class WebXRProtocolError(ValueError):
    """A message that does not follow the WebXR page's protocol; ``reason`` is in REASONS."""

    def __init__(self, reason: str, message: str):
        self.reason = check_name("WebXR protocol error reason", reason, REASONS)
        super().__init__(f"{message} [{reason}]")


class HandMsg(msgspec.Struct, forbid_unknown_fields=True):
    """One hand's joints as sent (flat lists; ``None`` for a joint without a pose)."""

    p: list[float | None]
    q: list[float | None]
    r: list[float | None]
    pinch: bool = False


class HandsMsg(msgspec.Struct, forbid_unknown_fields=True):
    v: int
    type: Literal["hands"]
    seq: int
    t: float
    paused: bool
    hands: dict[str, HandMsg | None]


class HelloMsg(msgspec.Struct, forbid_unknown_fields=True):
    v: int
    type: Literal["hello"]
    agent: str = ""
    page: str = ""


class SessionMsg(msgspec.Struct, forbid_unknown_fields=True):
    v: int
    type: Literal["session"]
    state: Literal["started", "ended"]
    mode: str = ""


_TYPES: dict[str, type[msgspec.Struct]] = {
    "hands": HandsMsg,
    "hello": HelloMsg,
    "session": SessionMsg,
}


class HandSample(msgspec.Struct, frozen=True):
    """One hand as parsed: ``positions`` (25, 3) and ``orientations`` (25, 4, x y z w) in the
    WebXR reference space, ``radii`` (25,); NaN rows where the joint had no pose."""

    positions: np.ndarray
    orientations: np.ndarray
    radii: np.ndarray
    pinch: bool

    @property
    def tracked(self) -> np.ndarray:
        return np.isfinite(self.positions).all(axis=1)


class HandsMessage(msgspec.Struct, frozen=True):
    """A parsed ``hands`` message: ``t_source`` in seconds (page clock, Unix epoch)."""

    seq: int
    t_source: float
    paused: bool
    hands: dict[str, HandSample]


def _decode(payload: str | bytes) -> dict:
    if isinstance(payload, (bytes, bytearray, memoryview)):
        raise WebXRProtocolError("binary", "binary messages are not part of the protocol")
    if not isinstance(payload, str):
        raise TypeError(f"message must be str, got {type(payload).__name__}")
    if len(payload) > MAX_MESSAGE_BYTES:
        raise WebXRProtocolError(
            "too_long", f"message of {len(payload)} chars, at most {MAX_MESSAGE_BYTES}"
        )
    try:
        obj = msgspec.json.decode(payload)
    except msgspec.DecodeError as exc:
        raise WebXRProtocolError("not_json", f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise WebXRProtocolError("not_object", f"a message is a JSON object, got {type(obj)}")
    return obj


def _joint_array(
    values: list[float | None], width: int, side: str, field: str, n: int = N_WEBXR_JOINTS
) -> np.ndarray:
    if len(values) != n * width:
        raise WebXRProtocolError(
            "wrong_shape",
            f"{side} hand {field!r}: {len(values)} numbers, expected {n * width} "
            f"({n} joints x {width})",
        )
    out = np.array(values, dtype=np.float64).reshape(n, width)  # None -> NaN
    missing = np.isnan(out)
    partial = missing.any(axis=1) & ~missing.all(axis=1)
    if partial.any():
        i = int(np.flatnonzero(partial)[0])
        raise WebXRProtocolError(
            "partial_joint",
            f"{side} hand {field!r}: joint {i} ({WEBXR_JOINTS[i]}) is partly null",
        )
    return out  # JSON has no NaN or inf: every number here is finite


def _hand_sample(side: str, hand: HandMsg) -> HandSample:
    positions = _joint_array(hand.p, 3, side, "p")
    orientations = _joint_array(hand.q, 4, side, "q")
    radii = _joint_array(hand.r, 1, side, "r")[:, 0]
    has_pose = ~np.isnan(positions[:, 0])
    if not (
        np.array_equal(has_pose, ~np.isnan(orientations[:, 0]))
        and np.array_equal(has_pose, ~np.isnan(radii))
    ):
        raise WebXRProtocolError(
            "partial_joint", f"{side} hand: a joint has a position but no orientation or radius"
        )
    if (np.abs(positions[has_pose]) > MAX_ABS_COORD_M).any():
        raise WebXRProtocolError(
            "too_far", f"{side} hand: a joint is more than {MAX_ABS_COORD_M} m from the origin"
        )
    norms = np.linalg.norm(orientations[has_pose], axis=1)
    if (np.abs(norms - 1.0) > QUAT_NORM_TOLERANCE).any():
        raise WebXRProtocolError(
            "bad_orientation", f"{side} hand: a joint orientation is not a unit quaternion"
        )
    lo, hi = RADIUS_RANGE_M
    r = radii[has_pose]
    if ((r <= lo) | (r > hi)).any():
        raise WebXRProtocolError(
            "bad_radius", f"{side} hand: a joint radius is outside ({lo}, {hi}] m"
        )
    return HandSample(positions, orientations, radii, bool(hand.pinch))


def parse_message(payload: str | bytes) -> HandsMessage | HelloMsg | SessionMsg:
    """One WebSocket message -> a parsed message; raises :class:`WebXRProtocolError`."""
    obj = _decode(payload)
    version = obj.get("v")
    if version != PROTOCOL_VERSION or isinstance(version, bool):
        raise WebXRProtocolError(
            "unknown_version",
            f"protocol version {version!r}, this detector speaks {PROTOCOL_VERSION}",
        )
    kind = obj.get("type")
    if kind not in _TYPES:
        raise WebXRProtocolError(
            "unknown_type", f"message type {kind!r} is not one of {', '.join(MESSAGE_TYPES)}"
        )
    try:
        msg = msgspec.convert(obj, _TYPES[kind])
    except msgspec.ValidationError as exc:
        raise WebXRProtocolError("schema", f"{kind} message: {exc}") from None
    if not isinstance(msg, HandsMsg):
        return msg
    if not (math.isfinite(msg.t) and msg.t > 0):
        raise WebXRProtocolError("bad_time", f"frame time {msg.t!r} ms is not a positive number")
    hands = {}
    for side, hand in msg.hands.items():
        if side not in SIDES:
            raise WebXRProtocolError(
                "unknown_hand", f"hand {side!r} is not one of {', '.join(SIDES)}"
            )
        if hand is not None:
            hands[side] = _hand_sample(side, hand)
    return HandsMessage(msg.seq, msg.t / 1e3, msg.paused, hands)


def hand_frames(message: HandsMessage, t_receive: float) -> list[HandFrame]:
    """A ``hands`` message -> one :class:`HandFrame` per side (right, left), through the
    ``webxr25`` layout. A hand absent from the message is a frame with every joint untracked
    (NaN), a joint without a pose is untracked: never zeros."""
    frames = []
    for side in SIDES:
        sample = message.hands.get(side)
        positions = sample.positions if sample is not None else np.full((N_WEBXR_JOINTS, 3), np.nan)
        frames.append(
            to_hand_frame(
                "webxr25",
                positions,
                side,
                message.t_source,
                t_receive,
                pinch=bool(sample is not None and sample.pinch),
                paused=message.paused,
            )
        )
    return frames


def _flat(values: np.ndarray, has_pose: np.ndarray) -> list[float | None]:
    """Rows of ``values`` flattened, None for the rows without a pose."""
    rows = np.asarray(values, dtype=np.float64).reshape(len(has_pose), -1)
    return [float(x) if has_pose[i] else None for i, row in enumerate(rows) for x in row]


def encode_hands(
    t_ms: float,
    hands: dict[str, np.ndarray | None],
    *,
    seq: int = 0,
    paused: bool = False,
    pinch: dict[str, bool] | None = None,
    orientations: dict[str, np.ndarray] | None = None,
    radius_m: float = 0.01,
) -> str:
    """The page's ``hands`` message for WebXR joint positions (side -> (25, 3), NaN rows for
    joints without a pose, or None): what the page sends, for tests and benchmarks. Identity
    orientations unless given."""
    out: dict[str, dict | None] = {}
    for side, points in hands.items():
        if points is None:
            out[side] = None
            continue
        points = np.asarray(points, dtype=np.float64)
        has_pose = np.isfinite(points).all(axis=1)
        quats = (orientations or {}).get(side)
        quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(points), 1)) if quats is None else quats
        radii = np.full(len(points), radius_m)

        out[side] = {
            "p": _flat(points, has_pose),
            "q": _flat(quats, has_pose),
            "r": _flat(radii, has_pose),
            "pinch": bool((pinch or {}).get(side, False)),
        }
    message = {
        "v": PROTOCOL_VERSION,
        "type": "hands",
        "seq": seq,
        "t": t_ms,
        "paused": paused,
        "hands": out,
    }
    return msgspec.json.encode(message).decode()
