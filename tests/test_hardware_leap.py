"""LEAP hand driver and Dynamixel bus emulator, through the real ``dynamixel_sdk``.

Everything here runs against :mod:`beavr_sim.hardware.leap.emulator` on a pseudo-terminal;
no test touches a real LEAP hand.
"""

from __future__ import annotations

import math
import os
import random
import re
import time

import numpy as np
import pytest
from dynamixel_sdk import GroupSyncRead, PacketHandler, PortHandler
from dynamixel_sdk.robotis_def import COMM_SUCCESS
from hypothesis import given, settings
from hypothesis import strategies as st
from waiting import HANG_GUARD_S

from beavr_sim.hardware.device import DeviceError
from beavr_sim.hardware.leap.config import (
    RAD_PER_COUNT,
    LeapHandConfig,
    counts_to_model,
    model_to_counts,
)
from beavr_sim.hardware.leap.driver import LeapHand, _Port
from beavr_sim.hardware.leap.emulator import (
    ERR_ACCESS,
    ERR_DATA_RANGE,
    INST_WRITE,
    DynamixelEmulator,
    build_packet,
    crc16,
    stuff,
    unstuff,
)

TOL = 1e-9
# The SDK waits about 34 ms per reply; on a loaded CI machine the emulator thread can miss
# that now and then. Tests that are not about timeouts allow more.
REPLY_S = 1.0  # 0.25 lost a connect's write through two tries in a clean-clone run under load


def _cfg(port: str, **kwargs) -> LeapHandConfig:
    return LeapHandConfig(port=port, **({"reply_timeout_s": REPLY_S} | kwargs))


def _open_sdk_port(path: str) -> PortHandler:
    port = _Port(path, REPLY_S)  # the SDK's PortHandler with the longer reply timeout
    assert port.openPort() and port.setBaudRate(4_000_000)
    return port


@pytest.fixture
def emu():
    with DynamixelEmulator() as e:
        yield e


@pytest.fixture
def hand(emu):
    h = LeapHand(_cfg(emu.port))
    h.connect()
    yield h
    h.disconnect()


def _new_goals(emu: DynamixelEmulator, since: int, n: int = 16) -> list[int]:
    """The next ``n`` goal counts the emulator logs after index ``since`` (a sync write has no
    reply: the emulator may still be handling it when the call returns)."""
    assert _wait_until(lambda: len(emu.goal_log) >= since + n), emu.goal_log[since:]
    return [c for _, _, c in emu.goal_log[since : since + n]]


def _wait_until(cond, timeout: float = HANG_GUARD_S) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


# --- conversions ------------------------------------------------------------------------------


def test_flat_hand_is_2048_counts():
    assert model_to_counts(np.zeros(16)).tolist() == [2048] * 16
    assert counts_to_model(np.array([2048, 3072, 1024])) == pytest.approx(
        [0, math.pi / 2, -math.pi / 2]
    )


@given(st.lists(st.integers(-1_048_575, 1_048_575), min_size=1, max_size=32))
def test_counts_round_trip_is_exact(counts):
    c = np.array(counts, dtype=np.int64)
    assert np.array_equal(model_to_counts(counts_to_model(c)), c)


@given(st.lists(st.floats(-3.0, 3.0), min_size=1, max_size=32))
def test_model_round_trip_within_half_a_count(q):
    back = counts_to_model(model_to_counts(np.array(q)))
    assert np.all(np.abs(back - np.array(q)) <= RAD_PER_COUNT / 2 + TOL)


# --- config -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"port": ""}, "port"),
        ({"baudrate": 4_000_001}, "baudrate"),
        ({"motor_ids": (0, 0)}, "motor_ids"),
        ({"motor_ids": ()}, "motor_ids"),
        ({"variant": "mini"}, "variant"),
        ({"current_limit_ma": 0}, "current_limit_ma"),
        ({"current_limit_ma": 5000}, "current_limit_ma"),
        ({"kp": -1}, "kp"),
        ({"kd": 20000}, "kd"),
        ({"side_gain": 0.0}, "side_gain"),
        ({"side_gain": float("nan")}, "side_gain"),
        ({"side_motor_ids": (99,)}, "side_motor_ids"),
        ({"lower": (0.0,) * 15}, "lower"),
        ({"upper": (float("inf"),) * 16}, "upper"),
        ({"lower": (1.0,) * 16, "upper": (0.0,) * 16}, "lower"),
        ({"timeout_s": 0.0}, "timeout_s"),
        ({"reply_timeout_s": -1.0}, "reply_timeout_s"),
        ({"retries": -1}, "retries"),
        ({"joint_names": ("a",)}, "joint_names"),
    ],
)
def test_config_validation_names_the_field(kwargs, field):
    base = {"port": "/dev/ttyUSB0"} | kwargs
    with pytest.raises(ValueError, match=rf"LeapHandConfig\.{field} must"):
        LeapHandConfig(**base)


def test_variant_message_lists_valid_values():
    with pytest.raises(ValueError, match=r"\['full', 'lite'\]"):
        LeapHandConfig(port="/dev/ttyUSB0", variant="mini")


def test_config_gains_and_currents():
    cfg = LeapHandConfig(port="p")
    assert cfg.gains(0) == (450, 0, 150) and cfg.gains(4) == cfg.gains(8) == (450, 0, 150)
    assert cfg.gains(1) == (600, 0, 200)
    assert cfg.goal_current_ma == 550
    assert LeapHandConfig(port="p", variant="lite").goal_current_ma == 350
    assert LeapHandConfig(port="p", variant="lite", current_limit_ma=420).goal_current_ma == 420


# --- emulator protocol, checked against the SDK's own packet code -----------------------------


class _CapturePort:
    """Just enough of a PortHandler for the SDK's txPacket to write into."""

    is_using = False

    def __init__(self) -> None:
        self.sent = b""

    def clearPort(self) -> None:
        pass

    def writePort(self, packet) -> int:
        self.sent = bytes(packet)
        return len(packet)


def test_crc_matches_sdk():
    ph = PacketHandler(2.0)
    rng = random.Random(1)
    for _ in range(50):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 60)))
        assert crc16(data) == ph.updateCRC(0, data, len(data))


def _sdk_packet(dxl_id: int, addr: int, data: list[int]) -> bytes:
    port = _CapturePort()
    PacketHandler(2.0).writeTxOnly(port, dxl_id, addr, len(data), data)
    return port.sent


def test_packets_match_sdk():
    data = [0x10, 0x02, 0x00, 0x00, 0xFF, 0xFF, 0x00, 0xFD]
    assert build_packet(3, INST_WRITE, bytes([116, 0, *data])) == _sdk_packet(3, 116, data)


def test_stuffing_matches_sdk_algorithm():
    ph = PacketHandler(2.0)
    data = [0xFF, 0xFF, 0xFD, 0x01, 0xFF, 0xFF, 0xFD, 0xFD]
    unstuffed = list(_sdk_packet(3, 116, data))
    stuffed = ph.addStuffing(unstuffed)  # the SDK's own stuffing, return value used
    n = len(stuffed)  # includes the two CRC slots
    crc = ph.updateCRC(0, stuffed, n - 2)
    expected = bytes(stuffed[: n - 2]) + crc.to_bytes(2, "little")
    ours = build_packet(3, INST_WRITE, bytes([116, 0, *data]))
    assert ours == expected
    assert ours.count(b"\xff\xff\xfd\xfd") == 2  # the header is never stuffed
    assert unstuff(stuff(bytes(data))) == bytes(data)


def test_sdk_txpacket_does_not_stuff():
    """Canary: dynamixel-sdk 4.1.0's txPacket drops addStuffing's result (a new list when the
    length changes), so instruction packets go out unstuffed. Harmless for LEAP goals (0..4095
    can never hold FF FF FD); if this fails, the SDK was fixed."""
    data = [0xFF, 0xFF, 0xFD, 0x01]
    assert b"\xff\xff\xfd\x01" in _sdk_packet(3, 116, data)


def test_sdk_reads_stuffed_status_and_both_sync_reads():
    # 0x00FDFFFF: its bytes FF FF FD force stuffing in the status packet the SDK must undo.
    positions = {0: 100, 1: 0x00FDFFFF, 2: -3, 3: 4095}
    with DynamixelEmulator(motor_ids=(0, 1, 2, 3), initial_position=positions) as e:
        port = _open_sdk_port(e.port)
        ph = PacketHandler(2.0)
        try:
            value, result, error = ph.read4ByteTxRx(port, 1, 132)
            assert (result, error, value) == (COMM_SUCCESS, 0, 0x00FDFFFF)
            reader = GroupSyncRead(port, ph, 132, 4)
            for i in positions:
                reader.addParam(i)
            for fast in (False, True):
                result = reader.fastSyncRead() if fast else reader.txRxPacket()
                assert result == COMM_SUCCESS
                got = {i: reader.getData(i, 132, 4) for i in positions}
                assert got == {i: v & 0xFFFFFFFF for i, v in positions.items()}
            assert [inst for _, _, inst in e.packet_log[-2:]] == [0x82, 0x8A]
        finally:
            port.closePort()


def test_eeprom_locked_with_torque_on_ram_writable(emu):
    port = _open_sdk_port(emu.port)
    ph = PacketHandler(2.0)
    try:
        assert ph.write1ByteTxRx(port, 2, 11, 5) == (COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, 2, 64, 1) == (COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(port, 2, 11, 3) == (COMM_SUCCESS, ERR_ACCESS)
        assert emu.motors[2].operating_mode == 5
        assert ph.write2ByteTxRx(port, 2, 84, 700) == (COMM_SUCCESS, 0)  # gains are RAM
        assert ph.write1ByteTxRx(port, 2, 132, 0) == (COMM_SUCCESS, ERR_ACCESS)  # read-only
        assert ph.write1ByteTxRx(port, 2, 64, 7) == (COMM_SUCCESS, ERR_DATA_RANGE)
        # Goal position is accepted with torque off, but the motor does not move.
        assert ph.write4ByteTxRx(port, 3, 116, 3000) == (COMM_SUCCESS, 0)
        emu.advance(time.monotonic() + 0.05)  # the motor model runs 50 ms, however loaded
        assert emu.motors[3].position == 2048.0 and emu.motors[3].goal_position == 3000
    finally:
        port.closePort()


def test_garbage_on_the_bus_is_dropped_and_the_bus_recovers(emu):
    fd = os.open(emu.port, os.O_RDWR | os.O_NOCTTY)
    try:
        good = build_packet(5, 0x01)
        bad_crc = good[:-1] + bytes([good[-1] ^ 0xFF])
        huge_length = b"\xff\xff\xfd\x00\x05\xff\xff"
        rng = random.Random(7)
        noise = bytes(rng.randrange(256) for _ in range(300))
        partial = b"\xff\xff\xfd\x00\x07\x40\x00\x02\x84"  # promises 64 bytes, stops
        os.write(fd, noise + huge_length + bad_crc + noise[:40] + partial)
        # The emulator took it all in and gave up on the partial packet at the end.
        assert _wait_until(lambda: emu.parser.dropped > 0 and not emu.parser.buffer)
    finally:
        os.close(fd)
    port = _open_sdk_port(emu.port)
    ph = PacketHandler(2.0)
    try:
        model, result, _ = ph.ping(port, 5)
        assert result == COMM_SUCCESS and model == emu.motors[5].model_number
    finally:
        port.closePort()
    assert emu.faults == [] and emu._thread is not None and emu._thread.is_alive()
    assert emu.parser.dropped > 0


# --- driver -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("variant", "current"), [("full", 550), ("lite", 350)])
def test_connect_sets_mode_gains_and_current(variant, current):
    start = {i: 1500 + 40 * i for i in range(16)}
    with DynamixelEmulator(initial_position=start) as e:
        for m in e.motors.values():
            m.goal_position = 3000  # stale, from an earlier session
        with LeapHand(_cfg(e.port, variant=variant)) as h:
            assert h.connected
            for i, m in e.motors.items():
                side = i in (0, 4, 8)
                assert m.operating_mode == 5
                assert (m.kp, m.ki, m.kd) == ((450, 0, 150) if side else (600, 0, 200))
                assert m.goal_current == current
                assert m.torque_enable == 1
                # Torque went off before the EEPROM write, and on only at the end.
                addrs = [a for a, _, _ in m.writes]
                assert addrs.index(64) < addrs.index(11) and addrs[-1] == 64
                # Goal = present before torque on: connecting does not move the hand.
                assert m.goal_position == start[i]
            e.advance(time.monotonic() + 0.05)  # the motor model runs 50 ms, however loaded
            assert all(m.present_position == start[i] for i, m in e.motors.items())
            assert h.read_positions() == pytest.approx(counts_to_model(list(start.values())))
        assert not h.connected


def test_stream_targets_converge_and_big_step_diverges():
    with DynamixelEmulator(max_velocity_rad_s=2.0) as emu, LeapHand(_cfg(emu.port)) as h:
        target = np.linspace(-0.4, 1.2, 16)
        n = len(emu.goal_log)
        sent = h.send_positions(target)
        assert sent == pytest.approx(target, abs=RAD_PER_COUNT / 2)
        # Right after a 1.2 rad step (0.6 s at 2 rad/s) the motor lags, at its capped current.
        assert abs(h.read_positions()[-1] - sent[-1]) > 0.6
        emu.advance()  # the read above was answered after the write: bring the model to now
        assert emu.motors[15].present_current == 550
        assert _wait_until(lambda: np.allclose(h.read_positions(), sent, atol=1e-12))
        # The present position reads whole counts: it may arrive half a count before the motor
        # stops (under load on this machine it did); the current falls to zero once it has.
        assert _wait_until(lambda: (emu.advance(), emu.motors[15].present_current == 0)[1])
        assert h.commands_sent == 1 and h.errors == 0
        assert _new_goals(emu, n) == model_to_counts(sent).tolist()


def test_clipping_is_reported_in_the_returned_targets(emu):
    lower = tuple([-0.3] * 16)
    upper = tuple([1.0] * 15 + [0.5])
    with LeapHand(_cfg(emu.port, lower=lower, upper=upper)) as h:
        q = np.full(16, 0.2)
        q[0], q[15], q[7] = -2.0, 3.0, 9.0
        n = len(emu.goal_log)
        sent = h.send_positions(q)
        assert sent[0] >= -0.3 and sent[0] == pytest.approx(-0.3, abs=RAD_PER_COUNT)
        assert sent[15] <= 0.5 and sent[15] == pytest.approx(0.5, abs=RAD_PER_COUNT)
        assert sent[7] <= 1.0 and sent[7] == pytest.approx(1.0, abs=RAD_PER_COUNT)
        assert sent[3] == pytest.approx(0.2, abs=RAD_PER_COUNT / 2)
        assert np.array_equal(counts_to_model(_new_goals(emu, n)), sent)


def test_unlimited_targets_stay_within_one_turn(emu, hand):
    n = len(emu.goal_log)
    sent = hand.send_positions(np.array([100.0, -100.0, 1e300] + [0.0] * 13))
    assert _new_goals(emu, n)[:3] == [4095, 0, 4095]
    assert sent[1] == pytest.approx(-math.pi)


def test_missing_motor_id_names_it():
    with DynamixelEmulator(motor_ids=tuple(i for i in range(16) if i != 9)) as e:
        h = LeapHand(_cfg(e.port, timeout_s=0.1))
        with pytest.raises(
            DeviceError, match=r"motor id\(s\) \[9\] .*power supply.*baudrate"
        ) as err:
            h.connect()
        assert e.port in str(err.value)
        assert not h.connected
        # Nothing was set up: the failure came before any write.
        assert all(m.torque_enable == 0 and m.writes == [] for m in e.motors.values())


def test_nonexistent_port_raises_device_error():
    h = LeapHand(LeapHandConfig(port="/dev/does-not-exist-leap"))
    with pytest.raises(DeviceError, match=r"cannot open serial port '/dev/does-not-exist-leap'"):
        h.connect()
    assert not h.connected
    h.disconnect()


def test_calls_before_connect_raise_device_error():
    h = LeapHand(LeapHandConfig(port="/dev/ttyUSB0"))
    for call in (h.read_positions, h.hold, lambda: h.send_positions(np.zeros(16))):
        with pytest.raises(DeviceError, match="not connected"):
            call()


def test_vanished_port_raises_device_error_quickly(emu, hand):
    hand.send_positions(np.zeros(16))
    emu.vanish()
    for call in (hand.read_positions, lambda: hand.send_positions(np.full(16, 0.1)), hand.hold):
        # Quickly: the port's own failure, at once - not a reply waited out and asked again.
        with pytest.raises(DeviceError, match=rf"serial port '{re.escape(emu.port)}' failed while"):
            call()
        assert hand.retries == 0
    assert hand.errors == 3 and hand.commands_sent == 1
    hand.disconnect()
    hand.disconnect()
    assert not hand.connected


def test_caught_up_says_whether_a_sync_write_has_reached_the_servos(emu, hand):
    """A sync write gets no reply, so the call returns before the emulator has handled it;
    ``caught_up(hand.bytes_sent)`` is what a test waits on instead of a fixed sleep. Holding
    the emulator's lock keeps it mid-handling: whether the bytes are still in the pty or
    already read, they are not handled."""
    assert _wait_until(lambda: emu.caught_up(hand.bytes_sent))
    n_goals = len(emu.goal_log)
    sent_before = hand.bytes_sent
    with emu.lock:  # the serving thread cannot handle what it reads
        hand.send_positions(np.full(16, 0.2))
        assert hand.bytes_sent > sent_before
        for _ in range(50):  # before and after the thread reads the bytes
            assert not emu.caught_up(hand.bytes_sent)
            time.sleep(0.002)
        assert len(emu.goal_log) == n_goals
    assert _wait_until(lambda: emu.caught_up(hand.bytes_sent))
    assert len(emu.goal_log) == n_goals + 16  # handled: no further wait needed


def test_bytes_sent_counts_over_a_reconnect(emu, hand):
    """The writer's count survives the port being closed and opened again, so a wait on
    ``caught_up`` stays true to what was written."""
    hand.send_positions(np.full(16, 0.1))
    before = hand.bytes_sent
    hand.disconnect()
    assert hand.bytes_sent == before
    hand.connect()
    hand.send_positions(np.full(16, 0.1))
    assert hand.bytes_sent > before
    assert _wait_until(lambda: emu.caught_up(hand.bytes_sent))


def test_waiting_for_a_reply_sleeps_instead_of_polling_the_port():
    """The SDK polls a non-blocking port until the reply window ends: thousands of reads (a
    core) per silent request, which starve whatever must answer. Ours sleeps until a byte or
    the window's end, and the SDK still gives up at that end."""
    master, slave = os.openpty()  # a bus where nothing answers
    try:
        port = _Port(os.ttyname(slave), 0.05)
        assert port.openPort() and port.setBaudRate(4_000_000)
        reads = 0
        read = port.ser.read

        def counted(n):
            nonlocal reads
            reads += 1
            return read(n)

        port.ser.read = counted
        _, result, _ = PacketHandler(2.0).ping(port, 1)
        port.closePort()
    finally:
        os.close(master), os.close(slave)
    assert result != COMM_SUCCESS  # no reply: a timeout, as before
    assert reads <= 3, f"{reads} reads of the port in one 50 ms reply window"


@pytest.mark.parametrize("retries", [0, 1])
def test_a_lost_reply_is_retried_once(emu, retries):
    with LeapHand(_cfg(emu.port, retries=retries)) as h:
        emu.drop_replies(1)
        if retries:
            assert h.read_positions().shape == (16,)
        else:
            with pytest.raises(DeviceError, match=r"no present position from motor 0"):
                h.read_positions()
        assert (h.retries, h.errors) == (retries, 1 - retries)
        emu.drop_replies(10)  # a hand that went quiet: fails after retries + 1 tries
        with pytest.raises(DeviceError, match="check the hand's power"):
            h.read_positions()
        emu.drop_replies(0)
        assert h.read_positions().shape == (16,)


def test_motor_error_byte_raises_device_error(emu, hand):
    hand.read_positions()
    emu.inject_error(3, 0x80)
    with pytest.raises(DeviceError, match=r"motor 3 reports .*Hardware error"):
        hand.read_positions()
    emu.inject_error(3, 0)
    assert hand.read_positions().shape == (16,)


@pytest.mark.parametrize(
    "bad", [np.full(16, np.nan), np.zeros(15), np.zeros((2, 16)), [np.inf] + [0.0] * 15]
)
def test_bad_targets_raise_value_error_and_send_nothing(emu, hand, bad):
    before = len(emu.goal_log)
    with pytest.raises(ValueError, match="leap_hand"):
        hand.send_positions(bad)
    hand.read_positions()  # a round trip: whatever went out before it has been handled
    assert len(emu.goal_log) == before and hand.commands_sent == 0


def test_hold_resends_last_target_or_measured_pose():
    start = {i: 2048 + 10 * i for i in range(16)}
    with DynamixelEmulator(initial_position=start) as e, LeapHand(_cfg(e.port)) as h:
        n = len(e.goal_log)
        h.hold()
        assert h.holding
        assert _new_goals(e, n) == list(start.values())
        n = len(e.goal_log)
        sent = h.send_positions(np.full(16, 0.3))
        assert not h.holding
        _new_goals(e, n)
        n = len(e.goal_log)
        h.hold()
        assert h.holding and np.array_equal(h.last_target, sent)
        assert _new_goals(e, n) == model_to_counts(sent).tolist()


@pytest.mark.parametrize("torque_off", [False, True])
def test_disconnect_keeps_torque_unless_asked(emu, torque_off):
    h = LeapHand(_cfg(emu.port, torque_off_on_disconnect=torque_off))
    h.connect()
    h.disconnect()
    h.disconnect()
    assert all(m.torque_enable == (0 if torque_off else 1) for m in emu.motors.values())


# --- property: nothing outside the limits ever reaches the bus --------------------------------

_RNG = np.random.default_rng(3)
_LOWER = tuple(float(x) for x in _RNG.uniform(-1.2, 0.0, 16))
_UPPER = tuple(float(x) for x in _RNG.uniform(0.05, 2.0, 16))


@pytest.fixture(scope="module")
def limited():
    with DynamixelEmulator() as e:
        h = LeapHand(_cfg(e.port, lower=_LOWER, upper=_UPPER))
        h.connect()
        yield e, h
        h.disconnect()


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False), min_size=16, max_size=16
    )
)
def test_every_goal_received_lies_within_the_limits(limited, q):
    e, h = limited
    n = len(e.goal_log)
    sent = h.send_positions(np.array(q))
    counts = np.array(_new_goals(e, n))
    assert [i for _, i, _ in e.goal_log[n:]] == list(range(16))
    lo_counts = (np.array(_LOWER) + np.pi) / RAD_PER_COUNT
    hi_counts = (np.array(_UPPER) + np.pi) / RAD_PER_COUNT
    assert np.all(counts >= lo_counts - 1e-6) and np.all(counts <= hi_counts + 1e-6)
    assert np.array_equal(counts_to_model(counts), sent)
