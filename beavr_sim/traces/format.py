"""VR traces: recorded or synthesised hand tracking in an MCAP file.

One channel per stream, JSON messages with a JSON Schema (viewable in Foxglove and other MCAP
tools), zstd-compressed chunks; the log time of each message is its ``t_source`` in ns:

- ``/hands/right``, ``/hands/left``: a :class:`~beavr_sim.wire.hand.HandFrame`; joints in
  metres rounded to 0.1 mm, ``null`` for an untracked joint;
- ``/control/resolution`` (``"high"`` / ``"low"``), ``/control/pause`` (``true`` = paused):
  the headset's buttons, written when they change.

A metadata record named ``beavr_sim`` holds :class:`TraceMetadata`. See ``docs/formats.md``.

A file cut short (a copy interrupted, a disk full, a writer killed) raises
:class:`TraceTruncatedError` saying where it ends and how many frames before that are readable;
:func:`salvage_trace` reads them (whole records, from whole chunks and the readable start of a
cut one) and :func:`recover_trace` writes them as a complete trace
(``python -m beavr_sim.traces recover``).
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.wire.hand import JOINT_NAMES, N_JOINTS, RESOLUTIONS, SIDES, HandFrame

FORMAT_VERSION = "1"
METADATA_NAME = "beavr_sim"
SOURCES = ("synth", "record")
CONTROLS = ("resolution", "pause")
#: Joint coordinates are rounded to this many decimals of a metre (0.1 mm).
JOINT_DECIMALS = 4
HAND_TOPICS = {side: f"/hands/{side}" for side in SIDES}
CONTROL_TOPICS = {name: f"/control/{name}" for name in CONTROLS}
HAND_SCHEMA_NAME = "beavr_sim.HandFrame"

HAND_JSON_SCHEMA: dict[str, Any] = {
    "title": HAND_SCHEMA_NAME,
    "description": "One tracked hand: right-handed Z-up metres; joints in canonical order "
    f"({', '.join(JOINT_NAMES)}); null = untracked.",
    "type": "object",
    "properties": {
        "side": {"enum": list(SIDES)},
        "t_source": {"type": "number", "description": "source time, s"},
        "t_receive": {"type": "number", "description": "receive time, s"},
        "joints": {
            "type": "array",
            "minItems": N_JOINTS,
            "maxItems": N_JOINTS,
            "items": {
                "oneOf": [
                    {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
                    {"type": "null"},
                ]
            },
        },
        "pinch": {"type": "boolean"},
        "resolution": {"enum": list(RESOLUTIONS)},
        "paused": {"type": "boolean"},
    },
    "required": ["side", "t_source", "t_receive", "joints", "pinch", "resolution", "paused"],
}
CONTROL_JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "resolution": {
        "title": "beavr_sim.Resolution",
        "type": "object",
        "properties": {"value": {"enum": list(RESOLUTIONS)}},
        "required": ["value"],
    },
    "pause": {
        "title": "beavr_sim.Pause",
        "type": "object",
        "properties": {"value": {"type": "boolean", "description": "true: teleop paused"}},
        "required": ["value"],
    },
}


class TraceError(ValueError):
    """A trace file that is missing, corrupt, truncated or not a beavr_sim trace."""


class TraceTruncatedError(TraceError):
    """A trace file cut short; ``salvage`` is what is readable before the cut."""

    def __init__(self, message: str, salvage: Salvage):
        super().__init__(message)
        self.salvage = salvage


@dataclass(frozen=True)
class TraceMetadata:
    """What a trace holds and how it was made (the ``beavr_sim`` MCAP metadata record).

    ``frame_rate_hz``: hand frames per second per side; None lets :class:`TraceWriter` fill in
    the measured rate. ``generator``: the synthesiser's parameters (JSON-serialisable).
    """

    source: str
    frame_rate_hz: float | None = None
    task: str = ""
    embodiment: str = ""
    seed: int | None = None
    generator: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_name("trace source", self.source, SOURCES)
        if self.frame_rate_hz is not None and not (
            math.isfinite(self.frame_rate_hz) and self.frame_rate_hz > 0
        ):
            raise ValueError(f"frame_rate_hz must be positive or None, got {self.frame_rate_hz!r}")
        if self.seed is not None and (
            isinstance(self.seed, bool) or not isinstance(self.seed, int)
        ):
            raise ValueError(f"seed must be an int or None, got {self.seed!r}")
        try:
            json.dumps(self.generator, allow_nan=False)
        except (TypeError, ValueError) as err:
            raise ValueError(f"generator parameters must be JSON-serialisable: {err}") from None

    def to_record(self) -> dict[str, str]:
        """The MCAP metadata (string -> string)."""
        return {
            "format_version": FORMAT_VERSION,
            "source": self.source,
            "frame_rate_hz": "" if self.frame_rate_hz is None else repr(float(self.frame_rate_hz)),
            "task": self.task,
            "embodiment": self.embodiment,
            "seed": "" if self.seed is None else str(self.seed),
            "generator": json.dumps(self.generator, sort_keys=True, separators=(",", ":")),
        }

    @classmethod
    def from_record(cls, record: dict[str, str]) -> TraceMetadata:
        version = record.get("format_version")
        if version != FORMAT_VERSION:
            raise TraceError(
                f"trace format_version {version!r} is not supported (expected {FORMAT_VERSION!r})"
            )
        try:
            return cls(
                source=record["source"],
                frame_rate_hz=float(record["frame_rate_hz"])
                if record.get("frame_rate_hz")
                else None,
                task=record.get("task", ""),
                embodiment=record.get("embodiment", ""),
                seed=int(record["seed"]) if record.get("seed") else None,
                generator=json.loads(record.get("generator") or "{}"),
            )
        except (KeyError, ValueError, TypeError) as err:
            raise TraceError(f"bad '{METADATA_NAME}' metadata record {record!r}: {err}") from None


class _HandRecord(msgspec.Struct, forbid_unknown_fields=False):
    side: str
    t_source: float
    t_receive: float
    joints: list[tuple[float, float, float] | None]
    pinch: bool
    resolution: str
    paused: bool


class _ControlRecord(msgspec.Struct):
    value: str | bool


def _log_time_ns(t: float, what: str) -> int:
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"{what} must be a finite time >= 0 s to be an MCAP log time, got {t!r}")
    return round(t * 1e9)


def hand_to_json(frame: HandFrame) -> bytes:
    """Compact JSON of a hand frame (joints rounded to 0.1 mm, null when untracked)."""
    joints = np.round(frame.joints, JOINT_DECIMALS) + 0.0  # + 0.0: no "-0.0"
    record = {
        "side": frame.side,
        "t_source": frame.t_source,
        "t_receive": frame.t_receive,
        "joints": [p.tolist() if ok else None for p, ok in zip(joints, frame.tracked, strict=True)],
        "pinch": bool(frame.pinch),
        "resolution": frame.resolution,
        "paused": bool(frame.paused),
    }
    return json.dumps(record, separators=(",", ":"), allow_nan=False).encode()


def hand_from_json(data: bytes) -> HandFrame:
    """Inverse of :func:`hand_to_json`; raises ValueError on bad data."""
    try:
        record = msgspec.json.decode(data, type=_HandRecord)
    except msgspec.DecodeError as err:
        raise ValueError(str(err)) from None
    if len(record.joints) != N_JOINTS:
        raise ValueError(f"hand frame has {len(record.joints)} joints, expected {N_JOINTS}")
    tracked = np.array([p is not None for p in record.joints])
    joints = np.array([p if p is not None else (np.nan,) * 3 for p in record.joints])
    return HandFrame(
        side=record.side,
        t_source=record.t_source,
        t_receive=record.t_receive,
        joints=joints,
        tracked=tracked,
        pinch=record.pinch,
        resolution=record.resolution,
        paused=record.paused,
    )


def _check_control(name: str, value: object) -> str | bool:
    check_name("control", name, CONTROLS)
    if name == "resolution":
        return check_name("resolution", value, RESOLUTIONS)
    if not isinstance(value, bool):
        raise ValueError(f"pause value must be a bool (True = paused), got {value!r}")
    return value


class TraceWriter:
    """Writes a trace; use as a context manager (the file is finished even on an exception).

    Messages may come in any order (readers sort by log time). The metadata record is
    written on :meth:`close`, so a ``None`` frame rate can be filled in from the frames.
    """

    def __init__(self, path: str | os.PathLike, metadata: TraceMetadata):
        from mcap.writer import CompressionType, Writer

        if not isinstance(metadata, TraceMetadata):
            raise TypeError(f"metadata must be a TraceMetadata, got {type(metadata).__name__}")
        self.path = Path(path)
        self.metadata = metadata
        self.counts = {topic: 0 for topic in [*HAND_TOPICS.values(), *CONTROL_TOPICS.values()]}
        self._t_range: dict[str, list[float]] = {}
        self._file = open(self.path, "wb")  # closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="beavr_sim")
        self._channels: dict[str, int] = {}
        hand_schema = self._writer.register_schema(
            HAND_SCHEMA_NAME, "jsonschema", json.dumps(HAND_JSON_SCHEMA).encode()
        )
        for topic in HAND_TOPICS.values():
            self._channels[topic] = self._writer.register_channel(topic, "json", hand_schema)
        for name, topic in CONTROL_TOPICS.items():
            schema = CONTROL_JSON_SCHEMAS[name]
            schema_id = self._writer.register_schema(
                schema["title"], "jsonschema", json.dumps(schema).encode()
            )
            self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)
        self._closed = False

    def _add(self, topic: str, t: float, data: bytes) -> None:
        if self._closed:
            raise RuntimeError(f"TraceWriter for {self.path} is closed")
        ns = _log_time_ns(t, f"{topic} time")
        self._writer.add_message(self._channels[topic], ns, data, ns, self.counts[topic])
        self.counts[topic] += 1
        lo_hi = self._t_range.setdefault(topic, [t, t])
        lo_hi[0], lo_hi[1] = min(lo_hi[0], t), max(lo_hi[1], t)

    def write_hand(self, frame: HandFrame) -> None:
        if not isinstance(frame, HandFrame):
            raise TypeError(f"write_hand takes a HandFrame, got {type(frame).__name__}")
        self._add(HAND_TOPICS[frame.side], frame.t_source, hand_to_json(frame))

    def write_control(self, name: str, t: float, value: str | bool) -> None:
        """A button value at source time ``t``: resolution ``"high"``/``"low"``, pause bool."""
        value = _check_control(name, value)
        self._add(CONTROL_TOPICS[name], t, json.dumps({"value": value}).encode())

    def _measured_rate(self) -> float | None:
        rates = []
        for topic in HAND_TOPICS.values():
            lo, hi = self._t_range.get(topic, (0.0, 0.0))
            if self.counts[topic] >= 2 and hi > lo:
                rates.append((self.counts[topic] - 1) / (hi - lo))
        return round(max(rates), 3) if rates else None

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            metadata = self.metadata
            if metadata.frame_rate_hz is None:
                metadata = replace(metadata, frame_rate_hz=self._measured_rate())
            self.metadata = metadata
            self._writer.add_metadata(METADATA_NAME, metadata.to_record())
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class TraceReader:
    """Reads a trace written by :class:`TraceWriter`; raises :class:`TraceError` if it cannot.

    ``metadata``, ``counts`` (messages per channel topic), ``duration_s`` (first to last
    message) are read when opened; :meth:`events` streams the messages in time order.
    """

    def __init__(self, path: str | os.PathLike):
        from mcap.reader import make_reader

        self.path = Path(path)
        if not self.path.is_file():
            raise TraceError(f"no trace file at {self.path}")
        try:
            with open(self.path, "rb") as f:
                reader = make_reader(f)
                summary = reader.get_summary()
                if summary is None or summary.statistics is None:
                    raise _unreadable(
                        self.path,
                        f"{self.path}: MCAP file has no summary (truncated, or the writer was "
                        f"killed before it finished)",
                    )
                records = [m for m in reader.iter_metadata() if m.name == METADATA_NAME]
        except TraceError:
            raise
        except Exception as err:  # the mcap reader raises many kinds on bad bytes
            raise _unreadable(
                self.path, f"{self.path} is not a readable MCAP file: {err!r}"
            ) from err
        if not records:
            raise TraceError(
                f"{self.path} is not a beavr_sim trace: no '{METADATA_NAME}' metadata record"
            )
        self.metadata = TraceMetadata.from_record(dict(records[-1].metadata))
        stats = summary.statistics
        topics = {cid: ch.topic for cid, ch in summary.channels.items()}
        self.counts = {
            topic: stats.channel_message_counts.get(cid, 0) for cid, topic in topics.items()
        }
        self.duration_s = (
            (stats.message_end_time - stats.message_start_time) / 1e9
            if stats.message_count
            else 0.0
        )
        self.start_s = stats.message_start_time / 1e9 if stats.message_count else 0.0

    def measured_rate_hz(self) -> dict[str, float | None]:
        """Hand frames per second per side, from counts and duration (None if under 2)."""
        rates = {}
        for side, topic in HAND_TOPICS.items():
            n = self.counts.get(topic, 0)
            rates[side] = (n - 1) / self.duration_s if n >= 2 and self.duration_s > 0 else None
        return rates

    def events(self) -> Iterator[tuple[float, str, Any]]:
        """``(t_source, kind, payload)`` in time order: kind ``"hand"`` (payload HandFrame),
        ``"resolution"`` (``"high"``/``"low"``) or ``"pause"`` (bool). Other channels are
        skipped."""
        from mcap.reader import make_reader

        kinds = {topic: "hand" for topic in HAND_TOPICS.values()}
        kinds.update({topic: name for name, topic in CONTROL_TOPICS.items()})
        with open(self.path, "rb") as f:
            try:
                for _schema, channel, message in make_reader(f).iter_messages(
                    topics=list(kinds), log_time_order=True
                ):
                    kind = kinds[channel.topic]
                    t = message.log_time / 1e9
                    where = f"{self.path}: {channel.topic} message at t={t:.6f} s"
                    try:
                        if kind == "hand":
                            payload: Any = hand_from_json(message.data)
                            if HAND_TOPICS[payload.side] != channel.topic:
                                raise ValueError(f"a {payload.side} hand on {channel.topic}")
                        else:
                            value = msgspec.json.decode(message.data, type=_ControlRecord).value
                            payload = _check_control(kind, value)
                    except ValueError as err:
                        raise TraceError(f"{where} is invalid: {err}") from None
                    yield t, kind, payload
            except TraceError:
                raise
            except Exception as err:  # the mcap reader raises many kinds on bad bytes
                raise TraceError(f"{self.path} is corrupt: {err!r}") from err

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary (what ``python -m beavr_sim.traces info`` prints)."""
        return {
            "path": str(self.path),
            "channels": self.counts,
            "messages": sum(self.counts.values()),
            "start_s": self.start_s,
            "duration_s": self.duration_s,
            "measured_rate_hz": self.measured_rate_hz(),
            "metadata": {
                "source": self.metadata.source,
                "frame_rate_hz": self.metadata.frame_rate_hz,
                "task": self.metadata.task,
                "embodiment": self.metadata.embodiment,
                "seed": self.metadata.seed,
                "generator": self.metadata.generator,
            },
        }


# ---------------------------------------------------------------------------- truncated files
_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = 9  # opcode (1 byte) + length (8 bytes)


@dataclass(frozen=True)
class Salvage:
    """What is readable of a trace file, in time order.

    ``truncated_at``: the byte at which the first record the file cuts short starts (None: no
    record is cut short). ``metadata``: the ``beavr_sim`` record if it is readable (the
    writer puts it before the last chunk). ``invalid``: whole messages that did not decode.
    """

    path: Path
    size: int
    truncated_at: int | None
    metadata: TraceMetadata | None
    events: tuple[tuple[float, str, Any], ...]
    invalid: int = 0

    @property
    def hand_frames(self) -> int:
        return sum(kind == "hand" for _, kind, _ in self.events)

    @property
    def duration_s(self) -> float:
        return self.events[-1][0] - self.events[0][0] if self.events else 0.0


def _chunk_records(body: bytes, complete: bool) -> bytes:
    """The records of a chunk record's content ``body`` (cut short unless ``complete``): all
    of them, or as much of the start as decompresses."""
    from mcap.data_stream import ReadDataStream

    stream = ReadDataStream(io.BytesIO(body))
    try:
        for _ in range(3):  # message start and end time, uncompressed size
            stream.read8()
        stream.read4()  # crc
        compression = stream.read_prefixed_string()
        stream.read8()  # compressed size
    except Exception:  # the header itself is cut short
        return b""
    data = body[stream.count :]
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        try:  # a streaming decompressor returns what the bytes so far hold
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except zstandard.ZstdError:
            return b""
    if compression == "lz4" and complete:
        import lz4.frame

        return lz4.frame.decompress(data)
    return b""


def salvage_trace(path: str | os.PathLike) -> Salvage:
    """Every whole message of ``path`` up to where it is cut short (see :class:`Salvage`)."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Metadata

    path = Path(path)
    data = path.read_bytes()
    if not data.startswith(_MAGIC):
        raise TraceError(f"{path} is not an MCAP file (it does not start with the MCAP magic)")
    records = bytearray()  # the data section's records, chunks unpacked, in file order
    pos, cut = len(_MAGIC), None
    while pos < len(data):
        if pos + _RECORD_HEAD > len(data):
            cut = pos
            break
        opcode = data[pos]
        end = pos + _RECORD_HEAD + int.from_bytes(data[pos + 1 : pos + _RECORD_HEAD], "little")
        if opcode == Opcode.CHUNK:
            body = data[pos + _RECORD_HEAD : min(end, len(data))]
            records += _chunk_records(body, complete=end <= len(data))
        elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
            break  # the data section is whole
        elif end <= len(data):
            records += data[pos:end]
        if end > len(data):
            cut = pos
            break
        pos = end
    topics: dict[int, str] = {}
    metadata: TraceMetadata | None = None
    messages: list[tuple[int, str, bytes]] = []
    pos = 0
    while pos + _RECORD_HEAD <= len(records):
        opcode = records[pos]
        length = int.from_bytes(records[pos + 1 : pos + _RECORD_HEAD], "little")
        if pos + _RECORD_HEAD + length > len(records):
            break  # the cut one
        stream = ReadDataStream(io.BytesIO(bytes(records[pos + _RECORD_HEAD :][:length])))
        if opcode == Opcode.CHANNEL:
            channel = Channel.read(stream)
            topics[channel.id] = channel.topic
        elif opcode == Opcode.MESSAGE:
            message = Message.read(stream, length)
            if message.channel_id in topics:
                topic = topics[message.channel_id]
                messages.append((message.log_time, topic, message.data))
        elif opcode == Opcode.METADATA:
            record = Metadata.read(stream)
            if record.name == METADATA_NAME:
                try:
                    metadata = TraceMetadata.from_record(dict(record.metadata))
                except TraceError:
                    metadata = None
        pos += _RECORD_HEAD + length
    kinds = {topic: "hand" for topic in HAND_TOPICS.values()}
    kinds.update({topic: name for name, topic in CONTROL_TOPICS.items()})
    events: list[tuple[float, str, Any]] = []
    invalid = 0
    for log_time, topic, payload in sorted(messages, key=lambda m: m[0]):
        kind = kinds.get(topic)
        if kind is None:
            continue
        try:
            if kind == "hand":
                value: Any = hand_from_json(payload)
                if HAND_TOPICS[value.side] != topic:
                    raise ValueError(f"a {value.side} hand on {topic}")
            else:
                value = _check_control(
                    kind, msgspec.json.decode(payload, type=_ControlRecord).value
                )
        except (ValueError, msgspec.DecodeError):
            invalid += 1
            continue
        events.append((log_time / 1e9, kind, value))
    return Salvage(path, len(data), cut, metadata, tuple(events), invalid)


def _unreadable(path: Path, message: str) -> TraceError:
    """The error for a file the MCAP reader cannot open: :class:`TraceTruncatedError` when
    it is cut short, else ``message``."""
    try:
        salvage = salvage_trace(path)
    except Exception:  # not even the start is MCAP: the reader's message says enough
        return TraceError(message)
    if salvage.truncated_at is None:
        return TraceError(message)
    where = (
        f"{path} is truncated at byte {salvage.size} (the record from byte "
        f"{salvage.truncated_at} on is cut short)"
    )
    if not salvage.hand_frames:
        return TraceTruncatedError(f"{where}; no hand frame before the cut is readable", salvage)
    out = path.with_name(f"{path.stem}_recovered.mcap")
    return TraceTruncatedError(
        f"{where}; the first {salvage.hand_frames} hand frames ({salvage.duration_s:.2f} s) are "
        f"readable: python -m beavr_sim.traces recover {path} --out {out}",
        salvage,
    )


def recover_trace(
    path: str | os.PathLike,
    out: str | os.PathLike,
    task: str | None = None,
    embodiment: str | None = None,
) -> Salvage:
    """Write the readable messages of ``path`` to ``out`` as a complete trace, with the file's
    metadata if it is readable (else ``source="record"``); ``task`` / ``embodiment`` replace
    its fields."""
    if Path(out).resolve() == Path(path).resolve():
        raise ValueError(f"the recovered trace must go to another file than {path}")
    salvage = salvage_trace(path)
    if not salvage.events:
        raise TraceError(f"{path}: no readable messages to recover")
    metadata = salvage.metadata or TraceMetadata(source="record")
    if task is not None:
        metadata = replace(metadata, task=task)
    if embodiment is not None:
        metadata = replace(metadata, embodiment=embodiment)
    with TraceWriter(out, metadata) as writer:
        for t, kind, payload in salvage.events:
            if kind == "hand":
                writer.write_hand(payload)
            else:
                writer.write_control(kind, t, payload)
    return salvage
