"""xArm7 driver against the protocol emulator, through the real ``xarm.wrapper.XArmAPI``.

Everything here runs on 127.0.0.1 with ephemeral ports; nothing ran on a real xArm.
"""

from __future__ import annotations

import math
import re
import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from waiting import HANG_GUARD_S

from beavr_sim.hardware.device import DeviceError
from beavr_sim.hardware.xarm.config import XArmConfig
from beavr_sim.hardware.xarm.driver import (
    CONTROLLER_ERRORS,
    ServoCommandError,
    XArm7,
    controller_code_name,
)
from beavr_sim.hardware.xarm.emulator import XArmEmulator

RANGES = ((-3.0, 3.0), (-2.0, 2.0), (-3.0, 3.0), (0.0, 3.5), (-3.0, 3.0), (-1.5, 3.0), (-3.0, 3.0))
BOUNDARY = (700.0, -700.0, 600.0, -600.0, 900.0, -100.0)
# The SDK warns through the deprecated Logger.warn on every servo_j (its copy of the mode).
pytestmark = pytest.mark.filterwarnings("ignore:The 'warn' method is deprecated:DeprecationWarning")

STEP = 0.008  # rad per servo_j: under the 1 rad/s cap at the emulator's 10 ms nominal period


def _config(emu: XArmEmulator, **overrides) -> XArmConfig:
    kwargs = dict(
        host=emu.host,
        port=emu.port,
        collision_sensitivity=4,
        self_collision_detection=True,
        reduced_joint_ranges=RANGES,
        tcp_boundary_mm=BOUNDARY,
        max_joint_speed=1.0,
        max_joint_acc=15.0,
        connect_timeout_s=2.0,
        command_timeout_s=0.5,
    )
    kwargs.update(overrides)
    return XArmConfig(**kwargs)


@pytest.fixture
def emu():
    with XArmEmulator() as e:
        yield e


@pytest.fixture
def arm(emu):
    device = XArm7(_config(emu))
    device.connect()
    yield device
    device.disconnect()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ramp(arm: XArm7, goal: np.ndarray) -> np.ndarray:
    """Stream small steps from the measured pose to ``goal``; the last target sent."""
    q = arm.read_positions()
    n = int(np.ceil(np.max(np.abs(goal - q)) / STEP))
    sent = q
    for k in range(1, n + 1):
        sent = arm.send_positions(q + (goal - q) * k / n)
    return sent


class SteppingClock:
    """Monotonic seconds that advance ``step`` per read: a deadline passes after a fixed number
    of reads, however loaded the machine."""

    def __init__(self, step: float = 0.01) -> None:
        self.step = step
        self.now = 0.0

    def __call__(self) -> float:
        self.now += self.step
        return self.now


def _wait_until(predicate, timeout: float = HANG_GUARD_S) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


# ------------------------------------------------------------------------ connect


def test_connect_arrives_in_servo_mode_with_the_safety_set(emu, arm):
    assert emu.mode == 1
    assert emu.set_state_log[-1] == 0 and emu.state in (1, 2)  # started: moving or ready
    assert emu.enabled
    assert emu.collision_sensitivity == 4
    assert emu.self_collision_detection is True
    assert emu.reduced_mode is True
    assert emu.reduced_max_joint_speed == pytest.approx(1.0)
    assert emu.joint_max_acc == pytest.approx(15.0)
    assert np.allclose(emu.reduced_joint_ranges, RANGES, atol=1e-6)
    assert emu.tcp_boundary_mm == tuple(int(b) for b in BOUNDARY)
    assert emu.unknown_registers == []
    assert arm.fault is None


def test_reconnect_reuses_the_controller_and_other_settings_arrive(emu):
    cfg = _config(
        emu,
        collision_sensitivity=0,
        self_collision_detection=False,
        reduced_mode=False,
        reduced_joint_ranges=None,
        tcp_boundary_mm=None,
    )
    device = XArm7(cfg)
    for _ in range(2):  # a second TCP connection to the same controller
        device.connect()
        assert device.read_positions().shape == (7,)
        device.disconnect()
        device.disconnect()  # idempotent
    assert emu.collision_sensitivity == 0
    assert emu.self_collision_detection is False
    assert emu.reduced_mode is False and emu.mode == 1


# ----------------------------------------------------------------------- streaming


def test_stream_converges_at_bounded_speed(emu, arm):
    goal = np.array([0.3, -0.2, 0.25, 0.4, -0.3, 0.2, 0.1])
    t0 = time.monotonic()
    last = _ramp(arm, goal)
    assert emu.servo_log[-1][1] == tuple(last)
    assert not np.allclose(arm.read_positions(), goal, atol=1e-3)  # 1 rad/s: not there yet
    assert _wait_until(lambda: np.allclose(arm.read_positions(), goal, atol=1e-5))
    assert time.monotonic() - t0 > 0.35  # 0.4 rad at <= 1 rad/s
    assert arm.commands_sent == len(emu.servo_log) == emu.accepted_servo
    assert arm.errors == 0


def test_hold_resends_the_last_target_once(emu, arm):
    goal = np.full(7, 0.05)
    last = _ramp(arm, goal)
    n = len(emu.servo_log)
    arm.hold()
    assert len(emu.servo_log) == n + 1
    assert emu.servo_log[-1][1] == emu.servo_log[-2][1] == tuple(last)
    assert _wait_until(lambda: np.allclose(emu.joints, last, atol=1e-6))


def test_invalid_targets_raise_value_error_and_send_nothing(emu, arm):
    bad = [
        np.full(7, np.nan),
        np.array([0, 0, 0, np.inf, 0, 0, 0.0]),
        np.zeros(6),
        np.zeros((7, 1)),
        np.full(7, 1e39),  # finite in float64, not representable as fp32
    ]
    for q in bad:
        with pytest.raises(ValueError):
            arm.send_positions(q)
    assert emu.servo_log == []
    assert arm.commands_sent == 0


# -------------------------------------------------------------------------- faults


def test_joint_limit_error_is_named_and_the_session_holds(emu, arm):
    _ramp(arm, np.full(7, 0.02))
    n_before = emu.accepted_servo
    target = arm.read_positions()
    target[1] = 2.5  # joint 2 limit is 2.0944
    with pytest.raises(ServoCommandError, match=r"joint angle over limit \(code 23\)") as info:
        arm.send_positions(target)
    assert info.value.sent is not None and info.value.sent[1] == pytest.approx(2.5)
    assert emu.error_code == 23 and emu.state == 4
    assert arm.fault == (23, "joint angle over limit")
    n_log = len(emu.servo_log)
    with pytest.raises(ServoCommandError, match="recover") as info:
        arm.send_positions(arm.read_positions())
    assert info.value.sent is None and len(emu.servo_log) == n_log  # nothing reached the wire
    assert emu.accepted_servo == n_before
    arm.recover()
    assert arm.fault is None and emu.state in (1, 2)
    arm.send_positions(arm.read_positions() + 0.005)
    assert emu.accepted_servo == n_before + 1


def test_speed_error_on_a_jump(emu, arm):
    with pytest.raises(DeviceError, match=r"speed over limit \(code 24\)"):
        arm.send_positions(arm.read_positions() + 0.1)  # 10 rad/s at the 10 ms period
    assert emu.error_code == 24


def test_emulator_recovery_needs_clean_enable_and_start_as_the_sdk_sees_it(emu, arm):
    api = arm.api
    q = list(arm.read_positions() + 0.005)
    emu.inject_error(31)
    assert arm.fault == (31, "collision current")
    assert api.set_servo_angle_j(q, is_radian=True) == 1  # has error
    assert api.clean_error() == 0 and emu.error_code == 0
    assert api.set_servo_angle_j(q, is_radian=True) == 9  # stopped, motors off: not ready
    assert api.motion_enable(True) == 0
    assert api.set_servo_angle_j(q, is_radian=True) == 9  # still stopped
    assert emu.accepted_servo == 0 and len(emu.servo_log) == 3
    assert api.set_state(0) == 0
    assert api.set_servo_angle_j(q, is_radian=True) == 0
    assert emu.accepted_servo == 1


def test_injected_error_reaches_the_driver_and_warnings_do_not_stop_it(emu, arm):
    emu.inject_warning(11)
    assert arm.fault == (11, "command buffer full")
    arm.send_positions(arm.read_positions())  # a warning does not stop motion
    emu.inject_error(22)
    with pytest.raises(ServoCommandError, match=r"self-collision \(code 22\)"):
        arm.send_positions(arm.read_positions())
    arm.hold()  # faulted: the arm is stopped, nothing to re-send
    assert emu.accepted_servo == 1 and len(emu.servo_log) == 2


def test_kill_mid_run_raises_device_error_without_hanging(emu, arm):
    goal = np.full(7, 0.1)
    _ramp(arm, goal)
    assert arm.api._arm._cmd_timeout == arm.config.command_timeout_s  # the SDK's reply wait
    emu.kill()
    t0, retries = time.monotonic(), arm.retries
    # Bounded by command_timeout_s: at most `retries` repeats of a request that timed out,
    # then the SDK's code for the dead link (never a wait of its own).
    with pytest.raises(DeviceError, match=r"127\.0\.0\.1.*SDK code"):
        arm.send_positions(goal)
    with pytest.raises(DeviceError, match="SDK code"):
        arm.read_positions()
    assert arm.retries - retries <= arm.config.retries
    assert time.monotonic() - t0 < HANG_GUARD_S  # a hang guard, not a timing bound
    arm.fault  # noqa: B018 -- a property read must not raise after a dead link
    arm.disconnect()
    arm.disconnect()
    with pytest.raises(DeviceError, match="not connected"):
        arm.read_positions()


# ------------------------------------------------------------------------- connect


def test_refused_port_is_a_fast_device_error():
    port = _free_port()
    device = XArm7(XArmConfig(host="127.0.0.1", port=port, connect_timeout_s=2.0))
    with pytest.raises(DeviceError) as info:
        device.connect()
    msg = str(info.value)
    # The refusal itself, not the connect timeout running out.
    assert "cannot connect" in msg and "no answer within" not in msg
    assert f"127.0.0.1:{port}" in msg and "right" in msg
    assert "powered on" in msg and "IP" in msg and "emergency stop" in msg
    assert device.api is None


def test_silent_peer_and_unroutable_host_time_out_within_connect_timeout():
    with socket.socket() as silent:  # completes TCP handshakes, never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen(4)
        silent_host, silent_port = silent.getsockname()[:2]
        # The silent peer is given up on at connect_timeout_s on the driver's clock (the
        # error names it); an unroutable host times out the same way, or is refused at once
        # where no route exists.
        for host, port, said in (
            (silent_host, silent_port, r"no answer within 0\.5 s"),
            ("192.0.2.1", None, r"no answer within 0\.5 s|cannot connect"),  # TEST-NET-1
        ):
            clock = SteppingClock()
            config = XArmConfig(host=host, port=port, connect_timeout_s=0.5)
            device = XArm7(config, clock=clock)
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match=host.replace(".", r"\.")) as info:
                device.connect()
            assert re.search(said, str(info.value)), info.value
            assert clock.now <= 0.5 + 3 * clock.step, f"gave up {clock.now:.2f} s after the start"
            assert time.monotonic() - t0 < HANG_GUARD_S  # a hang guard, not a timing bound


def test_wire_framing_several_requests_per_connection_and_reconnects(emu):
    def request(sock: socket.socket, trans: int, register: int, params: bytes = b"") -> tuple:
        sock.sendall(struct.pack(">HHHB", trans, 2, 1 + len(params), register) + params)
        head = sock.recv(8)
        trans_id, prot, length, reg, flags = struct.unpack(">HHHBB", head)
        data = sock.recv(length - 2) if length > 2 else b""
        return trans_id, prot, length, reg, flags, data

    for _ in range(2):
        with socket.create_connection((emu.host, emu.port), timeout=2) as s:
            s.sendall(bytes([0, 0, 0, 1, 0, 2, 0, 0]))  # SDK heartbeat: no reply
            assert request(s, 0x1234, 13) == (0x1234, 2, 3, 13, 0x10, b"\x04")  # not ready, stopped
            trans_id, _, length, reg, _, data = request(s, 7, 42)
            assert (trans_id, length, reg) == (7, 30, 42)
            assert struct.unpack("<7f", data) == (0.0,) * 7
            assert request(s, 8, 42, bytes([3]))[2] == 2 + 3 * 28  # joint states: pos, vel, effort
            assert request(s, 9, 200)[4] & 0x08  # unknown register: invalid flag
    assert emu.unknown_registers == [200, 200]


# ---------------------------------------------------------------------- config/names


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"host": ""}, "host"),
        ({"port": 0}, "port"),
        ({"port": 70000}, "port"),
        ({"port": 8080, "enable_report": True}, "enable_report"),
        ({"collision_sensitivity": 6}, "collision_sensitivity"),
        ({"collision_sensitivity": True}, "collision_sensitivity"),
        ({"self_collision_detection": 1}, "self_collision_detection"),
        ({"max_joint_speed": 4.0}, "max_joint_speed"),
        ({"max_joint_speed": 0.0}, "max_joint_speed"),
        ({"max_joint_acc": 25.0}, "max_joint_acc"),
        ({"max_joint_acc": math.nan}, "max_joint_acc"),
        ({"connect_timeout_s": 0}, "connect_timeout_s"),
        ({"reduced_joint_ranges": RANGES[:6]}, "reduced_joint_ranges"),
        ({"reduced_joint_ranges": ((1.0, -1.0),) + RANGES[1:]}, "reduced_joint_ranges"),
        ({"reduced_joint_ranges": RANGES[:1] + ((-2.5, 2.0),) + RANGES[2:]}, "joint 2"),
        ({"tcp_boundary_mm": (1, 2, 3)}, "tcp_boundary_mm"),
        ({"tcp_boundary_mm": (-700, 700, 600, -600, 900, -100)}, "x_max"),
        ({"reduced_mode": False, "tcp_boundary_mm": BOUNDARY}, "reduced_mode"),
    ],
)
def test_config_validation_names_the_field(overrides, field):
    kwargs = {"host": "192.168.1.185", **overrides}
    with pytest.raises(ValueError, match=field):
        XArmConfig(**kwargs)


def test_config_normalises_sequences_and_defaults():
    cfg = XArmConfig(host="192.168.1.185", reduced_joint_ranges=[list(r) for r in RANGES])
    assert cfg.reduced_joint_ranges == RANGES and cfg.port is None and cfg.enable_report is False
    assert cfg.collision_sensitivity == 3 and cfg.max_joint_speed == 2.5


def test_controller_code_names():
    assert [controller_code_name(c) for c in (1, 2, 3)] == ["emergency stop"] * 3
    assert controller_code_name(22) == "self-collision"
    assert controller_code_name(23) == "joint angle over limit"
    assert controller_code_name(24) == "speed over limit"
    assert controller_code_name(31) == "collision current"
    assert controller_code_name(35) == "safety boundary"
    assert controller_code_name(60) == "servo_j linear speed over limit"
    assert controller_code_name(999) == "controller error 999"
    assert 999 not in CONTROLLER_ERRORS


# ------------------------------------------------------------------------ property


@pytest.fixture(scope="module")
def streaming():
    """One connected arm for all examples, and every vector the driver reported as sent."""
    with XArmEmulator() as e:
        device = XArm7(_config(e))
        device.connect()
        yield e, device, set()
        device.disconnect()


_joint = st.floats(-1.0, 1.0, allow_nan=False)
_commands = st.lists(
    st.one_of(
        st.tuples(st.just("step"), arrays(np.float64, 7, elements=st.floats(-STEP, STEP))),
        st.tuples(st.just("jump"), arrays(np.float64, 7, elements=_joint)),
        st.tuples(st.just("absolute"), arrays(np.float64, 7, elements=st.floats(-7.0, 7.0))),
        st.tuples(
            st.just("bad"),
            st.sampled_from(
                [np.full(7, np.nan), np.full(7, -np.inf), np.zeros(8), np.full(7, 1e39)]
            ),
        ),
        st.tuples(st.just("hold"), st.none()),
        st.tuples(st.just("recover"), st.none()),
    ),
    max_size=20,
)


@settings(max_examples=40, deadline=None)
@given(commands=_commands)
def test_property_every_received_servo_j_is_finite_and_was_sent(streaming, commands):
    emu, arm, sent = streaming  # hold() may re-send a target of an earlier example
    arm.recover()
    last = arm.read_positions()
    for kind, value in commands:
        if kind == "hold":
            arm.hold()
            continue
        if kind == "recover":
            arm.recover()
            continue
        target = last + value if kind == "step" else value
        try:
            out = arm.send_positions(target)
        except ValueError:
            assert kind == "bad"
            continue
        except ServoCommandError as e:
            if e.sent is not None:
                sent.add(tuple(e.sent))
            continue
        assert kind != "bad"
        sent.add(tuple(out))
        last = out
    received = [q for _, q in emu.servo_log]
    assert all(math.isfinite(x) for q in received for x in q)
    assert set(received) <= sent
