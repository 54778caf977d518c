"""The Quest sockets against a fake headset: PUSH sockets that connect like the app and send
real keypoint strings, and a SUB that decodes the JPEG camera stream."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
import zmq
from PIL import Image
from waiting import HANG_GUARD_S

from beavr_sim.headset.address_gate import AddressGate, parse_allow_list
from beavr_sim.headset.quest_io import HeadsetImagePublisher, QuestReceiver, encode_jpeg
from beavr_sim.headset.quest_protocol import format_keypoints
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.wire.hand import N_JOINTS, HandFrame
from beavr_sim.wire.ports import PortConfig, TransportConfig


@pytest.fixture
def context():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.fixture
def config():
    return TransportConfig(ports=PortConfig.free())


class FakeHeadset:
    """PUSH sockets connecting to the PC like the BEAVR app does."""

    def __init__(self, context: zmq.Context, config: TransportConfig):
        self.sockets = {}
        for stream, port in (
            ("right", "quest_right"),
            ("left", "quest_left"),
            ("resolution", "quest_resolution"),
            ("pause", "quest_pause"),
        ):
            socket = context.socket(zmq.PUSH)
            socket.setsockopt(zmq.LINGER, 0)
            socket.connect(config.endpoint(port, bind=False))
            self.sockets[stream] = socket

    def send(self, stream: str, payload: str | bytes) -> None:
        self.sockets[stream].send(payload.encode() if isinstance(payload, str) else payload)


def hand(side: str, seed: int) -> HandFrame:
    rng = np.random.default_rng(seed)
    joints = np.array([0.35, 0.1 if side == "left" else -0.1, 1.2]) + rng.uniform(
        -0.09, 0.09, size=(N_JOINTS, 3)
    )
    tracked = np.ones(N_JOINTS, dtype=bool)
    tracked[[4, 25]] = False
    return HandFrame(side, 0.0, 0.0, np.where(tracked[:, None], joints, np.nan), tracked)


#: Sends of a five-frame burst until it arrives as one backlog (on a very busy machine the
#: receiver's I/O thread may hand it over in two parts).
BACKLOG_ATTEMPTS = 20


def poll_until(receiver: QuestReceiver, n: int, timeout_s: float = HANG_GUARD_S) -> list[HandFrame]:
    frames: list[HandFrame] = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < n and time.monotonic() < deadline:
        frames += receiver.poll(timeout_s=0.05)
    return frames


def test_receiver_parses_both_hands_and_stamps_buttons(context, config):
    right, left = hand("right", 1), hand("left", 2)
    with QuestReceiver(context, config) as receiver:
        headset = FakeHeadset(context, config)
        headset.send("resolution", "Low")
        headset.send("pause", "Low")
        # Buttons and hands travel on separate sockets: let the buttons land first.
        deadline = time.monotonic() + HANG_GUARD_S
        while min(receiver.received["pause"], receiver.received["resolution"]) < 1:
            assert time.monotonic() < deadline
            assert receiver.poll(0.02) == []
            time.sleep(0.01)
        t_before = time.monotonic()
        headset.send("right", format_keypoints(right, marker="absolute"))
        headset.send("left", format_keypoints(left, marker="relative"))
        frames = poll_until(receiver, 2)
        t_after = time.monotonic()
        assert sorted(f.side for f in frames) == ["left", "right"]
        for frame in frames:
            sent = right if frame.side == "right" else left
            assert np.array_equal(frame.tracked, sent.tracked)
            err = np.abs(frame.joints[sent.tracked] - sent.joints[sent.tracked]).max()
            assert err <= 0.5e-5 + 1e-12  # 5 decimals on the wire
            assert (frame.resolution, frame.paused) == ("low", True)
            assert t_before <= frame.t_receive <= t_after
            assert frame.t_source == frame.t_receive  # the app sends no timestamp
        # "None" on the resolution stream means no press: the last value stays.
        headset.send("resolution", "None")
        headset.send("pause", "High")
        deadline = time.monotonic() + 3.0
        while min(receiver.received["pause"], receiver.received["resolution"]) < 2:
            assert time.monotonic() < deadline
            assert receiver.poll(0.02) == []
        headset.send("right", format_keypoints(right))
        (frame,) = poll_until(receiver, 1)
        assert (frame.resolution, frame.paused) == ("low", False)
        assert receiver.alive("right") and receiver.alive("pause")
        assert not receiver.rejected
        for socket in headset.sockets.values():
            socket.close(linger=0)


def test_rejected_payloads_are_counted_with_reasons(context, config):
    calls = []
    validator = StreamValidator("quest", log_interval_s=60.0)
    with QuestReceiver(
        context, config, validator=validator, on_reject=lambda *a: calls.append(a)
    ) as receiver:
        headset = FakeHeadset(context, config)
        good = format_keypoints(hand("right", 3))
        comma = good.replace(",", ";").replace(".", ",").replace(";", ",")
        for bad in ("garbage", comma, good.rsplit("|", 1)[0] + ":", b"\xff\xfe"):
            headset.send("right", bad)
        headset.send("pause", "Maybe")
        headset.send("right", good)
        frames = poll_until(receiver, 1)
        deadline = time.monotonic() + HANG_GUARD_S
        while sum(receiver.rejected.values()) < 5 and time.monotonic() < deadline:
            frames += receiver.poll(0.02)
        assert len(frames) == 1 and frames[0].side == "right"
        assert dict(receiver.rejected) == {
            "no_marker": 1,
            "comma_decimal": 1,
            "wrong_joint_count": 1,
            "not_utf8": 1,
            "unknown_button": 1,
        }
        assert validator.rejected_by_reason == dict(receiver.rejected)
        assert sorted(c[0] for c in calls) == ["pause", "right", "right", "right", "right"]
        assert any("comma" in detail and "decimal" in detail for _, _, detail in calls)
        for socket in headset.sockets.values():
            socket.close(linger=0)


def test_a_backlog_yields_only_the_newest_frame(context, config):
    sent = [hand("right", seed) for seed in range(5)]
    with QuestReceiver(context, config) as receiver:
        headset = FakeHeadset(context, config)
        # A backlog: the five queued before a poll. Nothing shows the queue without taking
        # it, so send the five again until they arrived together (the first time, mostly).
        for _ in range(BACKLOG_ATTEMPTS):
            received, superseded = receiver.received["right"], receiver.superseded["right"]
            for frame in sent:
                headset.send("right", format_keypoints(frame))
            deadline, frames = time.monotonic() + HANG_GUARD_S, []
            while receiver.received["right"] < received + 5:
                assert time.monotonic() < deadline, "the five frames did not arrive"
                frames.append(receiver.poll(timeout_s=0.05))
            frames = [batch for batch in frames if batch]
            if len(frames) == 1:
                break
        (frame,) = frames[0]
        assert (receiver.superseded["right"] - superseded, len(frames)) == (4, 1)
        assert np.abs(frame.joints[frame.tracked] - sent[-1].joints[frame.tracked]).max() < 1e-5
        for socket in headset.sockets.values():
            socket.close(linger=0)
    with QuestReceiver(context, config, latest_only=False) as receiver:
        headset = FakeHeadset(context, config)
        for frame in sent:
            headset.send("right", format_keypoints(frame))
        assert len(poll_until(receiver, 5)) == 5
        for socket in headset.sockets.values():
            socket.close(linger=0)


def test_validator_refusals_drop_frames(context, config):
    class RefuseAll:
        def check(self, frame):
            return "stub_refusal"

        def reject(self, reason, detail=""):
            raise AssertionError("parse errors only")

    with QuestReceiver(context, config, validator=RefuseAll()) as receiver:
        headset = FakeHeadset(context, config)
        headset.send("left", format_keypoints(hand("left", 4)))
        deadline = time.monotonic() + 3.0
        while not receiver.rejected and time.monotonic() < deadline:
            assert receiver.poll(0.05) == []
        assert receiver.rejected == {"stub_refusal": 1}
        for socket in headset.sockets.values():
            socket.close(linger=0)


def test_a_second_receiver_on_the_same_ports_fails_clearly(context, config):
    with QuestReceiver(context, config), pytest.raises(OSError, match=r"PortConfig\.quest_right"):
        QuestReceiver(context, config)


def test_camera_stream_sends_decodable_jpegs_rate_limited(context, config):
    height, width = 360, 640
    u, v = np.meshgrid(np.linspace(0, 1, width), np.linspace(0, 1, height))
    image = (np.stack([u, v, 0.5 * (u + v)], axis=-1) * 255).astype(np.uint8)
    now = [0.0]
    with HeadsetImagePublisher(
        context, config, rate_hz=30.0, jpeg_quality=90, clock=lambda: now[0]
    ) as publisher:
        sub = context.socket(zmq.SUB)  # like the app: SUB, everything, connect
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(config.endpoint("headset_camera", bind=False))
        received = None
        for _ in range(200):  # slow joiner: keep publishing until the headset is subscribed
            now[0] += 1.0
            assert publisher.publish(image)
            if sub.poll(20):
                received = sub.recv()
                break
        assert received is not None
        decoded = np.asarray(Image.open(io.BytesIO(received)))
        assert received[:2] == b"\xff\xd8"  # a JPEG
        assert decoded.shape == (height, width, 3)
        assert np.abs(decoded.astype(float) - image).mean() < 2.0
        now[0] += 0.01
        assert not publisher.publish(image)  # under 1/30 s since the last one
        now[0] += 0.03
        assert publisher.publish(image)
        sub.close(linger=0)
    with pytest.raises(ValueError, match="uint8"):
        encode_jpeg(image.astype(np.float32))
    with pytest.raises(ValueError, match="jpeg_quality"):
        HeadsetImagePublisher(context, config, jpeg_quality=0)


def test_address_gate_drops_peers_not_on_the_allow_list(context, config):
    gate = AddressGate(context, parse_allow_list("127.0.0.1"))
    try:
        with QuestReceiver(context, config, gate=gate) as receiver:
            stranger = context.socket(zmq.PUSH)  # 127.0.0.2 stands in for another host
            stranger.setsockopt(zmq.LINGER, 0)
            port = config.ports.quest_pause
            stranger.connect(f"tcp://127.0.0.2:0;127.0.0.1:{port}")
            stranger.send(b"Low")
            deadline = time.monotonic() + 30.0  # a hang guard only
            while gate.refused["not_allowed"] < 1:
                assert time.monotonic() < deadline, "the gate never saw the stranger"
                receiver.poll(timeout_s=0.05)
            headset = FakeHeadset(context, config)  # from 127.0.0.1: on the list
            headset.send("pause", "Low")
            while receiver.received["pause"] < 1:
                assert time.monotonic() < deadline + 30.0, "the listed headset was not heard"
                receiver.poll(timeout_s=0.05)
            receiver.poll(timeout_s=0.05)
            assert receiver.received["pause"] == 1 and gate.accepted >= 1
            stranger.close()
            for s in headset.sockets.values():
                s.close()
    finally:
        gate.close()


def test_allow_list_parsing():
    assert parse_allow_list("any") is None
    assert parse_allow_list("10.0.0.5, 10.0.0.6") == {"10.0.0.5", "10.0.0.6"}
    with pytest.raises(ValueError, match="not an IP address"):
        parse_allow_list("quest.local")


def test_teleop_refuses_an_open_lan_headset_bind_that_mirrors_hardware():
    from beavr_sim.teleop.__main__ import build_parser
    from beavr_sim.teleop.session import SessionOptions

    argv = ["--task", "pour", "--headset-host", "0.0.0.0", "--mirror-hardware"]
    with pytest.raises(ValueError, match="--headset-allow HEADSET_IP"):
        SessionOptions.from_args(build_parser().parse_args(argv))
    listed = SessionOptions(task="pour", headset_host="0.0.0.0", headset_allow="10.0.0.5")
    assert listed.transport.headset_allow == {"10.0.0.5"}
    assert SessionOptions(task="pour").transport.headset_allow is None
