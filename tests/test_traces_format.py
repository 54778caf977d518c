"""MCAP VR traces: write -> read round trip, standard-tool readability, corrupt files, CLI."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import types

import numpy as np
import pytest
import zmq
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap.writer import Writer
from waiting import HANG_GUARD_S

from beavr_sim.naming import UnknownNameError
from beavr_sim.traces import TraceError, TraceMetadata, TraceReader, TraceWriter
from beavr_sim.traces.__main__ import main, record_trace
from beavr_sim.wire.hand import N_JOINTS, HandFrame
from beavr_sim.wire.ports import PortConfig, TransportConfig

RATE_HZ = 90.0
N_FRAMES = 60
METADATA = TraceMetadata(
    source="synth",
    frame_rate_hz=RATE_HZ,
    task="pour",
    embodiment="xarm7_leap_right",
    seed=7,
    generator={"speed_scale": 1.2, "noise_mm": 2.0, "phases": ["reach", "grasp"]},
)


def make_frames() -> list[HandFrame]:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(N_FRAMES):
        t = 1.0 + i / RATE_HZ
        for side in ("right", "left"):
            joints = rng.uniform(-0.5, 1.5, size=(N_JOINTS, 3))
            tracked = rng.uniform(size=N_JOINTS) > 0.1
            joints[~tracked] = np.nan
            frames.append(
                HandFrame(
                    side,
                    t,
                    t + 0.004,
                    joints,
                    tracked,
                    pinch=i % 7 == 0,
                    resolution="low" if i >= 30 else "high",
                    paused=i >= 50,
                )
            )
    return frames


@pytest.fixture(scope="module")
def trace_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("traces") / "trace.mcap"
    frames = make_frames()
    with TraceWriter(path, METADATA) as writer:
        writer.write_control("resolution", 1.0, "high")
        writer.write_control("pause", 1.0, False)
        for frame in reversed(frames):  # any order: readers sort by log time
            writer.write_hand(frame)
        writer.write_control("resolution", 1.0 + 30 / RATE_HZ, "low")
        writer.write_control("pause", 1.0 + 50 / RATE_HZ, True)
    return path


def test_round_trip_frames_order_and_metadata(trace_path):
    reader = TraceReader(trace_path)
    assert reader.metadata == METADATA
    assert reader.counts == {
        "/hands/right": N_FRAMES,
        "/hands/left": N_FRAMES,
        "/control/resolution": 2,
        "/control/pause": 2,
    }
    assert reader.duration_s == pytest.approx((N_FRAMES - 1) / RATE_HZ, abs=1e-9)
    assert reader.measured_rate_hz()["right"] == pytest.approx(RATE_HZ, rel=1e-6)
    events = list(reader.events())
    times = [t for t, _, _ in events]
    assert times == sorted(times)
    hands = [p for _, kind, p in events if kind == "hand"]
    expected = {(f.side, f.t_source): f for f in make_frames()}
    assert len(hands) == len(expected)
    worst = 0.0
    for frame in hands:
        sent = expected[(frame.side, frame.t_source)]
        assert np.array_equal(frame.tracked, sent.tracked)
        assert np.isnan(frame.joints[~sent.tracked]).all()
        worst = max(worst, np.abs(frame.joints[sent.tracked] - sent.joints[sent.tracked]).max())
        assert frame.t_receive == sent.t_receive
        assert (frame.pinch, frame.resolution, frame.paused) == (
            sent.pinch,
            sent.resolution,
            sent.paused,
        )
    assert 1e-6 < worst <= 0.5e-4 + 1e-12  # rounded to 0.1 mm, no more
    controls = [(round(t, 6), kind, p) for t, kind, p in events if kind != "hand"]
    assert controls == [
        (1.0, "resolution", "high"),
        (1.0, "pause", False),
        (round(1.0 + 30 / RATE_HZ, 6), "resolution", "low"),
        (round(1.0 + 50 / RATE_HZ, 6), "pause", True),
    ]


class JsonDecoderFactory(DecoderFactory):
    def decoder_for(self, message_encoding, schema):
        if message_encoding == "json" and schema is not None and schema.encoding == "jsonschema":
            return json.loads
        return None


def test_readable_by_standard_mcap_tools(trace_path):
    with open(trace_path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[JsonDecoderFactory()])
        summary = reader.get_summary()
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        (meta,) = list(reader.iter_metadata())
        assert meta.name == "beavr_sim" and meta.metadata["task"] == "pour"
        n = 0
        for schema, channel, message, decoded in reader.iter_decoded_messages("/hands/right"):
            assert json.loads(schema.data)["title"] == "beavr_sim.HandFrame"
            assert channel.message_encoding == "json"
            assert message.log_time == round(decoded["t_source"] * 1e9)
            assert len(decoded["joints"]) == N_JOINTS
            assert all(p is None or len(p) == 3 for p in decoded["joints"])
            assert len(message.data) < 1000  # compact: 26 joints at 0.1 mm
            n += 1
        assert n == N_FRAMES


def test_missing_and_corrupt_files_raise_trace_errors(trace_path, tmp_path):
    with pytest.raises(TraceError, match="no trace file"):
        TraceReader(tmp_path / "absent.mcap")
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(TraceError, match="not a readable MCAP"):
        TraceReader(garbage)
    data = trace_path.read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(TraceError):
        TraceReader(truncated)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(TraceError):
        TraceReader(empty)
    # A valid MCAP that is not ours.
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        writer = Writer(f)
        writer.start()
        writer.finish()
    with pytest.raises(TraceError, match="not a beavr_sim trace"):
        TraceReader(foreign)
    # A valid file with a bad message: the error names the channel and the time.
    bad = tmp_path / "bad_message.mcap"
    with open(bad, "wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema("beavr_sim.HandFrame", "jsonschema", b"{}")
        channel = writer.register_channel("/hands/right", "json", schema)
        writer.add_message(channel, 2_000_000_000, b'{"side": "right", "joints": []}', 0)
        writer.add_metadata("beavr_sim", METADATA.to_record())
        writer.finish()
    reader = TraceReader(bad)
    with pytest.raises(TraceError, match=r"/hands/right message at t=2\.000000 s is invalid"):
        list(reader.events())


def test_writer_and_metadata_validation(tmp_path):
    with pytest.raises(UnknownNameError, match="record, synth"):
        TraceMetadata(source="live")
    with pytest.raises(ValueError, match="JSON"):
        TraceMetadata(source="synth", generator={"f": object()})
    with TraceWriter(tmp_path / "w.mcap", TraceMetadata(source="record")) as writer:
        with pytest.raises(ValueError, match="high, low"):
            writer.write_control("resolution", 0.0, "medium")
        with pytest.raises(UnknownNameError, match="pause, resolution"):
            writer.write_control("volume", 0.0, 1)
        frame = make_frames()[0]
        from dataclasses import replace

        with pytest.raises(ValueError, match=">= 0"):
            writer.write_hand(replace(frame, t_source=-1.0))
        for i in range(11):  # 50 Hz: the writer fills in the measured rate
            writer.write_hand(replace(frame, t_source=i * 0.02))
    assert TraceReader(tmp_path / "w.mcap").metadata.frame_rate_hz == pytest.approx(50.0)


def test_info_cli(trace_path, capsys, tmp_path):
    assert main(["info", str(trace_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "synth trace" in lines[0] and "pour" in lines[0]
    summary = json.loads(lines[-1])
    assert summary["channels"]["/hands/left"] == N_FRAMES
    assert summary["duration_s"] == pytest.approx((N_FRAMES - 1) / RATE_HZ)
    assert summary["metadata"]["seed"] == 7
    assert summary["metadata"]["generator"]["phases"] == ["reach", "grasp"]
    # The module entry point, as a user runs it; a missing file exits 2 with the reason.
    done = subprocess.run(
        [sys.executable, "-m", "beavr_sim.traces", "info", str(tmp_path / "nope.mcap")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2 and "no trace file" in done.stderr


def test_synth_subcommand_delegates(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # were the real synth reached, it would write x.mcap here
    seen = []
    fake = types.ModuleType("beavr_sim.synthetic.trace")
    fake.main = lambda argv: seen.append(argv) or 0
    monkeypatch.setitem(sys.modules, "beavr_sim.synthetic.trace", fake)
    assert main(["synth", "--task", "pour", "--out", "x.mcap"]) == 0
    assert seen == [["--task", "pour", "--out", "x.mcap"]]


def test_record_from_a_fake_headset(tmp_path):
    from beavr_sim.headset.quest_protocol import format_keypoints

    config = TransportConfig(ports=PortConfig.free())
    payload = format_keypoints(make_frames()[0])
    stop, recording = threading.Event(), threading.Event()

    def headset() -> None:
        if not recording.wait(HANG_GUARD_S):  # the recorder's sockets are bound
            return
        context = zmq.Context()
        right = context.socket(zmq.PUSH)
        pause = context.socket(zmq.PUSH)
        for socket, port in ((right, "quest_right"), (pause, "quest_pause")):
            socket.setsockopt(zmq.LINGER, 0)
            socket.connect(config.endpoint(port, bind=False))
        i = 0
        while not stop.is_set():
            pause.send(b"Low" if i >= 20 else b"High")
            right.send(payload.encode())
            i += 1
            time.sleep(0.01)
        context.destroy(linger=0)

    thread = threading.Thread(target=headset)
    thread.start()
    out = tmp_path / "rec.mcap"
    try:
        # Until the recorder wrote the pause press and more than 20 hand frames, however
        # slowly the machine ran the 100 Hz headset; `seconds` is only a hang guard.
        counts = record_trace(
            out, config, seconds=HANG_GUARD_S, log=lambda *a: recording.set(),
            until=lambda c: c.get("/control/pause", 0) >= 2 and c.get("/hands/right", 0) > 20,
        )  # fmt: skip
    finally:
        stop.set()
        thread.join(timeout=5)
    reader = TraceReader(out)
    assert reader.metadata.source == "record"
    assert counts["/hands/right"] == reader.counts["/hands/right"] > 20
    assert reader.counts["/control/pause"] == 2  # False at the start, then True
    events = list(reader.events())
    assert events[0][0] == 0.0  # times from the first frame
    hands = [t for t, kind, _ in events if kind == "hand"]  # the rate the frames arrived at
    measured = (len(hands) - 1) / (hands[-1] - hands[0])
    assert reader.metadata.frame_rate_hz == pytest.approx(measured, abs=1e-3)
    pauses = [p for _, kind, p in events if kind == "pause"]
    assert pauses == [False, True]
