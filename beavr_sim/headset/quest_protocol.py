"""The BEAVR Quest app's wire formats: keypoint strings, resolution and pause buttons.

Keypoint string (one hand, one rendered frame)::

    <marker>:x,y,z|x,y,z|...|x,y,z:

``marker`` is ``relative`` or ``absolute`` (a label only), then 26 triples in the canonical
joint order (wrist first, palm second), metres in Unity's left-handed Y-up world frame.
Joints the headset does not track are sent as ``0,0,0``. The app sends no timestamp.

Parsing is strict: anything else raises a :class:`ProtocolError` whose ``reason`` is one of
:data:`REASONS` (short, for counting) and whose message says what was wrong.
"""

from __future__ import annotations

import re

import numpy as np

from beavr_sim.headset.layouts import unity_to_zup, zup_to_unity
from beavr_sim.naming import check_name
from beavr_sim.wire.hand import JOINT_NAMES, N_JOINTS, HandFrame

MARKERS = ("relative", "absolute")
#: Longest keypoint payload accepted (26 triples of long floats fit in about 2 KiB).
MAX_PAYLOAD_BYTES = 8192
#: Largest accepted |coordinate| in metres: the headset's tracking space is a room.
MAX_ABS_COORD_M = 10.0

#: Every ``ProtocolError.reason``.
REASONS = (
    "not_utf8",
    "too_long",
    "no_marker",
    "unknown_marker",
    "no_terminator",
    "wrong_joint_count",
    "wrong_triple",
    "comma_decimal",
    "not_a_number",
    "non_finite",
    "too_far",
    "untracked",
    "unknown_button",
)

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBER_RE = re.compile(_NUMBER, re.ASCII)
_TRIPLE = rf"{_NUMBER},{_NUMBER},{_NUMBER}"
_BODY_RE = re.compile(rf"{_TRIPLE}(?:\|{_TRIPLE}){{{N_JOINTS - 1}}}", re.ASCII)
# A field of a comma-decimal number: digits only (the integer or the fraction part); some
# locales (e.g. Swedish) write the minus sign as U+2212.
_COMMA_PART_RE = re.compile(r"[-+\u2212]?\d+(?:[eE][-+\u2212]?\d+)?", re.ASCII)
_NON_FINITE = {"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}
_NON_FINITE |= {"∞", "-∞", "+∞"}


class ProtocolError(ValueError):
    """A payload that does not follow the Quest app's protocol; ``reason`` is in REASONS."""

    def __init__(self, reason: str, message: str):
        self.reason = check_name("protocol error reason", reason, REASONS)
        super().__init__(f"{message} [{reason}]")


class KeypointParseError(ProtocolError):
    """A keypoint string that cannot be turned into a hand frame."""


def _decode(payload: bytes | str, what: str, error: type[ProtocolError]) -> str:
    if isinstance(payload, (bytes, bytearray, memoryview)):
        payload = bytes(payload)
        if len(payload) > MAX_PAYLOAD_BYTES:
            raise error("too_long", f"{what} of {len(payload)} bytes, at most {MAX_PAYLOAD_BYTES}")
        try:
            return payload.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise error("not_utf8", f"{what} is not UTF-8 text ({exc.reason})") from None
    if isinstance(payload, str):
        if len(payload) > MAX_PAYLOAD_BYTES:
            raise error("too_long", f"{what} of {len(payload)} chars, at most {MAX_PAYLOAD_BYTES}")
        return payload
    raise TypeError(f"{what} must be bytes or str, got {type(payload).__name__}")


def _short(text: str, n: int = 40) -> str:
    return repr(text if len(text) <= n else text[:n] + "...")


def _diagnose_body(body: str) -> None:
    """Raise the precise error for a body that failed the fast full-body match."""
    triples = body.split("|")
    split = [t.split(",") for t in triples]
    if "." not in body and any(
        len(fields) in (4, 5, 6) and all(_COMMA_PART_RE.fullmatch(f) for f in fields)
        for fields in split
    ):
        raise KeypointParseError(
            "comma_decimal",
            "numbers use ',' as the decimal separator (a headset set to a comma-decimal "
            "locale, e.g. German): set the headset's region to one that writes '0.123'",
        )
    if len(triples) != N_JOINTS:
        raise KeypointParseError(
            "wrong_joint_count", f"got {len(triples)} '|'-separated triples, expected {N_JOINTS}"
        )
    for i, fields in enumerate(split):
        where = f"joint {i} ({JOINT_NAMES[i]})"
        if len(fields) != 3:
            raise KeypointParseError(
                "wrong_triple",
                f"{where}: {_short(triples[i])} has {len(fields)} ','-separated fields, expected 3",
            )
        for f in fields:
            if f.strip().lower() in _NON_FINITE:
                raise KeypointParseError("non_finite", f"{where}: {f!r} is not a finite number")
            if not _NUMBER_RE.fullmatch(f):
                raise KeypointParseError(
                    "not_a_number", f"{where}: {_short(f)} is not a number like '-0.123'"
                )
    raise AssertionError(f"keypoint body failed to match but no fault found: {_short(body)}")


def parse_keypoints(
    payload: bytes | str,
    side: str,
    t_receive: float,
    t_source: float | None = None,
    resolution: str = "high",
    paused: bool = False,
) -> HandFrame:
    """One keypoint string -> :class:`HandFrame` (Z-up); ``t_source`` defaults to ``t_receive``.

    Joints sent as exactly ``0,0,0`` are flagged untracked (position NaN).
    """
    text = _decode(payload, "keypoint payload", KeypointParseError)
    marker, sep, rest = text.partition(":")
    if not sep or not marker:
        raise KeypointParseError(
            "no_marker", f"payload {_short(text)} does not start with 'relative:' or 'absolute:'"
        )
    if marker not in MARKERS:
        raise KeypointParseError(
            "unknown_marker", f"marker {_short(marker)} is not one of {', '.join(MARKERS)}"
        )
    if not rest.endswith(":"):
        raise KeypointParseError(
            "no_terminator", f"payload does not end with ':' (ends with {_short(text[-20:])})"
        )
    body = rest[:-1]
    if not _BODY_RE.fullmatch(body):
        _diagnose_body(body)
    points = np.array(body.replace("|", ",").split(","), dtype=np.float64).reshape(N_JOINTS, 3)
    if not np.isfinite(points).all():  # overflow, e.g. 1e999
        i = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise KeypointParseError("non_finite", f"joint {i} ({JOINT_NAMES[i]}) overflows a float")
    far = np.abs(points).max(axis=1) > MAX_ABS_COORD_M
    if far.any():
        i = int(np.flatnonzero(far)[0])
        raise KeypointParseError(
            "too_far",
            f"joint {i} ({JOINT_NAMES[i]}) at {points[i].tolist()} m: coordinates beyond "
            f"+-{MAX_ABS_COORD_M} m are not a tracked hand",
        )
    untracked = ~points.any(axis=1)
    if untracked.all():
        raise KeypointParseError("untracked", "every joint is 0,0,0: the hand is not tracked")
    points[untracked] = np.nan
    joints = unity_to_zup(points)
    t_source = t_receive if t_source is None else t_source
    return HandFrame(
        side, t_source, t_receive, joints, ~untracked, resolution=resolution, paused=paused
    )


def format_keypoints(frame: HandFrame, marker: str = "absolute", decimals: int = 5) -> str:
    """Inverse of :func:`parse_keypoints`: untracked joints are written as ``0,0,0``."""
    check_name("keypoint marker", marker, MARKERS)
    if not isinstance(decimals, int) or not 0 <= decimals <= 9:
        raise ValueError(f"decimals must be an int in 0..9, got {decimals!r}")
    points = zup_to_unity(np.where(frame.tracked[:, None], frame.joints, 0.0))
    if np.abs(points).max() > MAX_ABS_COORD_M:
        raise ValueError(f"a joint lies beyond +-{MAX_ABS_COORD_M} m: the parser would reject it")
    points = points + 0.0  # no "-0.00000" for untracked joints
    body = "|".join(",".join(f"{v:.{decimals}f}" for v in p) for p in points)
    return f"{marker}:{body}:"


def _parse_button(payload: bytes | str, what: str, values: dict[str, object]) -> object:
    text = _decode(payload, f"{what} payload", ProtocolError)
    if text not in values:
        raise ProtocolError(
            "unknown_button", f"{what} payload {_short(text)}, expected one of {', '.join(values)}"
        )
    return values[text]


def parse_resolution(payload: bytes | str) -> str | None:
    """Resolution button: ``High`` -> "high", ``Low`` -> "low", ``None`` -> None (no press)."""
    return _parse_button(payload, "resolution", {"High": "high", "Low": "low", "None": None})  # type: ignore[return-value]


def parse_pause(payload: bytes | str) -> bool:
    """Pause status: ``Low`` -> True (paused), ``High`` -> False (teleop continues)."""
    return bool(_parse_button(payload, "pause", {"High": False, "Low": True}))
