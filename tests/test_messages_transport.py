"""Wire messages (msgspec) and the ZeroMQ transport: round trips, validation, handshake,
conflation, liveness of a killed publisher."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import textwrap
import time

import msgspec
import numpy as np
import pytest
import zmq
from waiting import HANG_GUARD_S, wait_until

from beavr_sim.naming import UnknownNameError
from beavr_sim.wire.hand import N_JOINTS, HandFrame
from beavr_sim.wire.messages import (
    HandFrameMsg,
    JointCommandMsg,
    MessageError,
    RobotStateMsg,
    SessionMsg,
    decode,
    encode,
)
from beavr_sim.wire.ports import PortConfig, TransportConfig, free_tcp_ports
from beavr_sim.wire.transport import Heartbeat, Liveness, Publisher, Subscriber


@pytest.fixture
def context():
    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


def tcp_endpoint() -> str:
    return f"tcp://127.0.0.1:{free_tcp_ports(1)[0]}"


def hand_frame(side: str = "right", seed: int = 0) -> HandFrame:
    rng = np.random.default_rng(seed)
    joints = np.array([0.4, 0.0, 1.1]) + rng.uniform(-0.1, 0.1, size=(N_JOINTS, 3))
    tracked = np.ones(N_JOINTS, dtype=bool)
    tracked[[5, 17]] = False
    joints[~tracked] = np.nan
    return HandFrame(side, 12.25, 12.5, joints, tracked, pinch=True, resolution="low", paused=True)


def every_message() -> list:
    return [
        HandFrameMsg.from_frame(hand_frame()),
        JointCommandMsg(
            effector="right", t_source=1.5, t_command=1.52, positions=[0.1 * i for i in range(23)]
        ),
        JointCommandMsg(
            effector="left",
            t_source=2.0,
            t_command=2.1,
            positions=[],
            hold=True,
            reason="hand lost",
        ),
        RobotStateMsg(
            t=3.0, positions=[0.5, -0.25], velocities=[0.0, 1.0], success=True, guard_blocked=True
        ),
        SessionMsg(command="record_start", t=4.0),
    ]


# --- config -------------------------------------------------------------------------------


def test_port_config_matches_app_and_validates():
    ports = PortConfig()
    assert (ports.quest_right, ports.quest_left, ports.quest_resolution, ports.quest_pause) == (
        8087,
        8110,
        8095,
        8100,
    )
    assert (ports.headset_camera, ports.headset_graph) == (10505, 15001)
    assert len(set(map(ports.port, ports.names))) == len(ports.names)
    with pytest.raises(ValueError, match="both 8087"):
        PortConfig(commands=8087)
    with pytest.raises(ValueError, match=r"1\.\.65535"):
        PortConfig(session=70000)
    with pytest.raises(ValueError, match=r"1\.\.65535"):
        PortConfig(session=0)
    config = TransportConfig(host="127.0.0.1", headset_host="0.0.0.0")
    assert config.endpoint("quest_right", bind=True) == "tcp://0.0.0.0:8087"
    assert config.endpoint("quest_right", bind=False) == "tcp://127.0.0.1:8087"
    assert config.endpoint("commands", bind=True) == "tcp://127.0.0.1:5572"
    with pytest.raises(UnknownNameError, match="quest_left"):
        config.endpoint("quest_lft", bind=True)
    with pytest.raises(ValueError, match=r"0\.0\.0\.0"):
        TransportConfig(headset_host="*")
    with pytest.raises(ValueError, match="IPv4"):
        TransportConfig(host="300.1.1.1")
    free = PortConfig.free()
    assert len(set(map(free.port, free.names))) == len(free.names)


# --- messages -----------------------------------------------------------------------------


def test_hand_frame_msg_round_trip_is_exact():
    frame = hand_frame()
    msg = decode(encode(HandFrameMsg.from_frame(frame)), HandFrameMsg)
    back = msg.to_frame()
    assert np.array_equal(back.tracked, frame.tracked)
    t = frame.tracked
    assert np.array_equal(back.joints[t], frame.joints[t])  # float64 on the wire: exact
    assert np.isnan(back.joints[~t]).all()
    assert (back.side, back.t_source, back.t_receive) == ("right", 12.25, 12.5)
    assert (back.pinch, back.resolution, back.paused) == (True, "low", True)
    assert all(math.isfinite(v) for v in msg.joints)  # untracked go out as 0.0


@pytest.mark.parametrize("msg", every_message(), ids=lambda m: type(m).__name__)
def test_every_message_round_trips(msg):
    assert decode(encode(msg), type(msg)) == msg
    assert decode(encode(msg)) == msg  # the union of every message type


def _raw(**fields) -> bytes:
    return msgspec.msgpack.encode(fields)


@pytest.mark.parametrize(
    ("data", "expected", "match"),
    [
        (b"\xc1\x00", RobotStateMsg, "malformed"),
        (encode(SessionMsg(command="stop")), RobotStateMsg, r"'session'.*\$\.type"),
        (_raw(type="session", command="pauze"), SessionMsg, "Did you mean 'pause'"),
        (
            _raw(type="robot_state", t=1.0, positions=[math.nan], velocities=[0.0]),
            RobotStateMsg,
            "positions must be finite",
        ),
        (
            _raw(type="robot_state", t=1.0, positions=[1.0, 2.0], velocities=[0.0]),
            RobotStateMsg,
            "velocities needs 2",
        ),
        (
            _raw(type="joint_command", effector="right", t_source=1.0, t_command=1.0, positions=[]),
            JointCommandMsg,
            "non-empty unless hold",
        ),
        (
            _raw(
                type="joint_command",
                effector="right/arm",
                t_source=1.0,
                t_command=1.0,
                positions=[1.0],
            ),
            JointCommandMsg,
            "without '/'",
        ),
        (
            _raw(
                type="hand_frame",
                side="right",
                t_source=1.0,
                t_receive=1.0,
                joints=[0.0] * 77,
                tracked=[True] * 26,
            ),
            HandFrameMsg,
            "joints needs 78",
        ),
        (
            _raw(
                type="hand_frame",
                side="right",
                t_source=1.0,
                t_receive=1.0,
                joints=[math.inf] * 78,
                tracked=[True] * 26,
            ),
            HandFrameMsg,
            "joints must be finite",
        ),
        (
            _raw(
                type="hand_frame",
                side="up",
                t_source=1.0,
                t_receive=1.0,
                joints=[0.0] * 78,
                tracked=[True] * 26,
            ),
            HandFrameMsg,
            "Unknown side",
        ),
        (
            _raw(
                type="hand_frame",
                side="left",
                t_source=1.0,
                t_receive=1.0,
                joints=[0.0] * 78,
                tracked=[1] * 26,
            ),
            HandFrameMsg,
            "Expected `bool`",
        ),
    ],
)
def test_decode_rejects_with_a_clear_message(data, expected, match):
    with pytest.raises(MessageError, match=match):
        decode(data, expected)


def test_encode_refuses_non_messages():
    with pytest.raises(MessageError, match="HandFrameMsg"):
        encode({"type": "session", "command": "stop"})


# --- liveness helpers ---------------------------------------------------------------------


def test_liveness_and_heartbeat_with_a_fake_clock():
    now = [0.0]
    live = Liveness(0.3, clock=lambda: now[0])
    assert live.state() == "waiting" and not live.alive() and live.age_s() == math.inf
    live.beat()
    now[0] = 0.3
    assert live.state() == "alive"
    now[0] = 0.31
    assert live.state() == "dead"
    beat = Heartbeat(10.0, clock=lambda: now[0])
    due = []
    for t in (0.0, 0.05, 0.1, 0.15, 0.2, 0.29, 0.3, 1.0, 1.05, 1.1):
        now[0] = t
        due.append(beat.due())
    # 10 Hz: every 0.1 s; after the stall to t = 1.0 one beat, not a burst of seven.
    assert due == [True, False, True, False, True, False, True, True, False, True]
    with pytest.raises(ValueError, match="positive"):
        Heartbeat(0.0)


# --- transport ----------------------------------------------------------------------------


def test_every_message_over_tcp_and_inproc(context):
    for endpoint in (tcp_endpoint(), "inproc://messages"):
        with (
            Publisher(context, endpoint) as pub,
            Subscriber(context, endpoint, b"all", conflate=False) as sub,
        ):
            assert pub.wait_for_subscribers(1, timeout_s=2.0)
            for msg in every_message():
                pub.send(b"all", msg)
            received = [sub.recv(timeout_s=2.0) for _ in every_message()]
            assert received == every_message()
            assert (sub.received, sub.dropped, sub.last_topic) == (5, 0, b"all")


def test_handshake_delivers_the_very_first_message(context):
    endpoint = tcp_endpoint()
    with Publisher(context, endpoint) as pub:
        assert not pub.wait_for_subscribers(1, timeout_s=0.05)
        for i in range(5):  # five fresh subscribers, each gets the one message sent
            with Subscriber(context, endpoint, b"state", RobotStateMsg) as sub:
                assert pub.wait_for_subscribers(1, timeout_s=2.0, topic=b"state")
                pub.send(b"state", RobotStateMsg(t=float(i), positions=[], velocities=[]))
                assert sub.recv(timeout_s=2.0).t == float(i)
            deadline = time.monotonic() + 2.0  # unsubscription reaches the publisher
            while pub.subscriber_count() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert pub.subscriber_count() == 0


def test_topics_filter_exactly(context):
    endpoint = tcp_endpoint()
    with (
        Publisher(context, endpoint) as pub,
        Subscriber(context, endpoint, b"right", SessionMsg, conflate=False) as sub,
    ):
        assert pub.wait_for_subscribers(1, 2.0)
        pub.send(b"right2", SessionMsg(command="stop"))  # a prefix match must not leak in
        pub.send(b"right", SessionMsg(command="pause"))
        assert sub.recv(2.0).command == "pause"
        assert sub.recv(0.05) is None
    with Publisher(context, "inproc://bad") as pub, pytest.raises(ValueError, match="topic"):
        pub.send(b"has space", SessionMsg(command="stop"))


def test_malformed_messages_are_dropped_counted_and_survived(context):
    # inproc: a send has reached the subscriber's queue when it returns, so one recv_latest
    # below sees the good message and both bad ones around it (over TCP: a settle sleep).
    endpoint = "inproc://malformed"
    with (
        Publisher(context, endpoint) as pub,
        Subscriber(context, endpoint, b"state", RobotStateMsg, conflate=False) as sub,
    ):
        assert pub.wait_for_subscribers(1, 2.0)
        nan_hand = _raw(
            type="hand_frame",
            side="right",
            t_source=1.0,
            t_receive=1.0,
            joints=[math.nan] * 78,
            tracked=[True] * 26,
        )
        nan_state = _raw(type="robot_state", t=1.0, positions=[math.nan], velocities=[0.0])
        for bad in (b"state ", b"state \xc1", b"state " + nan_hand, b"state " + nan_state):
            pub._socket.send(bad)  # raw frames: Publisher.send only sends valid messages
        pub.send(b"state", RobotStateMsg(t=7.0, positions=[1.0], velocities=[0.0]))
        msg = sub.recv(timeout_s=2.0)
        assert msg == RobotStateMsg(t=7.0, positions=[1.0], velocities=[0.0])
        assert sub.dropped == 4 and sub.received == 1
        assert "finite" in sub.last_error
        pub._socket.send(b"state " + nan_state)  # recv_latest drops too, keeps the last good one
        pub.send(b"state", RobotStateMsg(t=8.0, positions=[1.0], velocities=[0.0]))
        pub._socket.send(b"state garbage")
        assert sub.recv_latest(timeout_s=1.0).t == 8.0  # one call drains all three
        assert sub.dropped == 6


def test_conflation_keeps_only_the_latest(context):
    # inproc: a send has reached every subscriber's queue when it returns, so the 100
    # messages are all queued before the first recv (over TCP that needs a settle sleep).
    endpoint = "inproc://conflation"
    with (
        Publisher(context, endpoint) as pub,
        Subscriber(context, endpoint, b"state", RobotStateMsg) as latest_only,
        Subscriber(context, endpoint, b"state", RobotStateMsg, conflate=False) as every,
    ):
        assert pub.wait_for_subscribers(2, 2.0, topic=b"state")
        for i in range(100):
            pub.send(b"state", RobotStateMsg(t=float(i), positions=[float(i)], velocities=[0.0]))
        assert latest_only.recv_latest(timeout_s=1.0).t == 99.0
        assert latest_only.received == 1  # the socket kept one message, not 100
        assert latest_only.recv() is None
        assert every.recv_latest(timeout_s=1.0).t == 99.0  # drain-and-keep-latest
        assert every.received == 100
    with pytest.raises(ValueError, match="exactly one topic"):
        Subscriber(context, endpoint, [b"right", b"left"])


def test_closed_publisher_is_reported_dead_within_the_timeout(context):
    endpoint = tcp_endpoint()
    pub = Publisher(context, endpoint)
    now = [100.0]  # the liveness clock: time passes when the test says so
    with Subscriber(
        context, endpoint, b"state", RobotStateMsg, liveness_timeout_s=0.2, clock=lambda: now[0]
    ) as sub:
        assert sub.liveness.state() == "waiting"
        assert pub.wait_for_subscribers(1, 2.0)
        for i in range(20):
            pub.send(b"state", RobotStateMsg(t=float(i), positions=[], velocities=[]))
        last: list = [None]

        def took_the_last() -> bool:  # a conflating socket: the newest message only
            last[0] = sub.recv(timeout_s=0.01) or last[0]
            return last[0] is not None and last[0].t == 19.0

        wait_until(took_the_last, "the last message sent")
        assert sub.alive()
        pub.close()
        assert sub.recv(timeout_s=0.05) is None  # nothing after the close
        now[0] += 0.19  # within the timeout: still alive
        assert sub.alive() and sub.recv() is None
        now[0] += 0.02  # past it: dead, with nothing received meanwhile
        assert sub.recv() is None and sub.liveness.state() == "dead"
        with pytest.raises(RuntimeError, match="closed"):
            pub.send(b"state", RobotStateMsg(t=0.0, positions=[], velocities=[]))


_PUBLISHER_SCRIPT = textwrap.dedent(
    """
    import sys, zmq
    from beavr_sim.wire.messages import RobotStateMsg
    from beavr_sim.wire.transport import Heartbeat, Publisher
    context = zmq.Context()
    pub = Publisher(context, sys.argv[1])
    beat = Heartbeat(100.0)
    i = 0
    while True:
        if beat.due():
            pub.send(b"state", RobotStateMsg(t=float(i), positions=[0.0], velocities=[0.0]))
            i += 1
        pub._socket.poll(2)
    """
)


def test_killed_publisher_process_is_reported_dead_and_a_restart_recovers(context):
    endpoint = tcp_endpoint()

    def start() -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-c", _PUBLISHER_SCRIPT, endpoint])

    timeout_s, step_s = 0.25, 0.01
    now = [100.0]  # the liveness clock: it advances step_s per receive below
    with Subscriber(
        context, endpoint, b"state", RobotStateMsg, liveness_timeout_s=timeout_s,
        clock=lambda: now[0],
    ) as sub:  # fmt: skip
        for round_ in range(2):  # second round: a restarted publisher is picked up again
            process = start()
            try:
                assert sub.recv(timeout_s=10.0) is not None, f"round {round_}: no message"
                for _ in range(10):
                    sub.recv_latest(timeout_s=0.02)
                assert sub.alive()
                process.send_signal(signal.SIGKILL)
                process.wait(timeout=5)
                hang_guard = time.monotonic() + HANG_GUARD_S
                while sub.alive():  # messages in flight at the kill may still come
                    sub.recv_latest(timeout_s=0.002)  # never raises
                    now[0] += step_s
                    assert time.monotonic() < hang_guard, "never reported dead"
                assert sub.liveness.state() == "dead"
                # Dead on the first check past the timeout since the last message.
                assert timeout_s < sub.liveness.age_s() <= timeout_s + step_s + 1e-9
            finally:
                process.kill()
                process.wait(timeout=5)
        assert sub.dropped == 0


def test_numpy_inputs_become_plain_lists():
    msg = JointCommandMsg(
        effector="right",
        t_source=np.float32(1.5),
        t_command=2,
        positions=np.arange(3, dtype=np.float32),
    )
    assert msg.positions == [0.0, 1.0, 2.0] and type(msg.t_source) is float
    assert decode(encode(msg), JointCommandMsg) == msg
    with pytest.raises(ValueError, match="flat list"):
        RobotStateMsg(t=0.0, positions=np.zeros((2, 2)), velocities=[0.0] * 4)
    with pytest.raises(TypeError, match="number"):
        SessionMsg(command="stop", t="now")


def test_fixtures_travel_to_the_operator_process_unchanged():
    """--multiprocess: the operator's IK gets the task's fixtures from the twin's states, the
    same obstacles the in-process loop reads from the env, through msgpack."""
    import gymnasium as gym

    from beavr_sim.operator.obstacles import fixture_obstacles
    from beavr_sim.teleop.process_config import fixtures_to_wire, obstacles_from_wire
    from beavr_sim.wire.messages import FixtureMsg, RobotStateMsg

    env = gym.make("beavr_sim/Pour-v0").unwrapped
    try:
        env.reset(seed=3)
        fixtures = fixtures_to_wire(env)
        assert fixtures, "Pour has a target cup"
        msg = RobotStateMsg(t=0.0, positions=[0.0], velocities=[0.0], fixtures=fixtures)
        back = msgspec.msgpack.decode(msgspec.msgpack.encode(msg), type=RobotStateMsg)
        assert obstacles_from_wire(back.fixtures) == fixture_obstacles(env.model, env.data)
    finally:
        env.close()
    shape = [6.0, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match="11 numbers"):
        FixtureMsg(name="box", pos=[0, 0, 0], quat=[1, 0, 0, 0], geoms=[shape[:-1]])
    with pytest.raises(ValueError, match="finite"):
        FixtureMsg(name="box", pos=[0, 0, 0], quat=[1, 0, 0, 0], geoms=[[*shape[:-1], np.nan]])
    with pytest.raises(ValueError, match="finite"):
        FixtureMsg(name="box", pos=[0, np.inf, 0], quat=[1, 0, 0, 0], geoms=[shape])
