"""RX-1 Feetech driver and STS bus emulator, through the real ``scservo_sdk``.

Everything here runs against :mod:`beavr_sim.hardware.feetech.emulator` on a pseudo-terminal;
no test touches a real RX-1 or a real STS3215.
"""

from __future__ import annotations

import json
import math
import os
import random
import re
import select
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scservo_sdk import (
    COMM_SUCCESS,
    SCS_TOHOST,
    SCS_TOSCS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
)
from waiting import HANG_GUARD_S

from beavr_sim.hardware.device import DeviceError
from beavr_sim.hardware.feetech.config import (
    EAR_SERVO_IDS,
    GROUPS,
    MULTI_TURN_MAX_COUNT,
    RX1_ANGLE_LIMITS,
    SERVOS_BY_ID,
    STS3215_NO_LOAD_RAD_S,
    FeetechConfig,
    allowed_counts,
    angle_to_counts,
    counts_to_angle,
    from_sign_magnitude,
    to_sign_magnitude,
)
from beavr_sim.hardware.feetech.driver import FeetechBus, _Port
from beavr_sim.hardware.feetech.emulator import (
    ERRBIT_OVERLOAD,
    INST_READ,
    INST_SYNC_WRITE,
    INST_WRITE,
    MULTI_TURN,
    ONE_TURN,
    FeetechEmulator,
    build_packet,
    checksum,
    decode,
    encode,
)
from beavr_sim.hardware.servo_model import step_towards

TOL = 1e-9
# The SDK busy-polls for about 34 ms per reply; on a loaded machine the emulator thread can miss
# that now and then. Tests that are not about timeouts allow more.
REPLY_S = 1.0  # 0.25 lost a connect's write through two tries in a clean-clone run under load
ARM = ("shoulder_pitch", "shoulder_roll", "arm_yaw", "elbow", "forearm_yaw", "wrist_pitch",
       "wrist_roll")  # fmt: skip
# The RX-1 table, written out once more by hand: (ids, directions, gears, joints).
RX1 = {
    "torso": ((1, 2, 3), (-1, 1, -1), (3, 3, 3), ("torso_yaw", "torso_pitch", "torso_roll")),
    "head": ((4, 5, 6), (-1, -1, -1), (1, 1, 1), ("neck_yaw", "neck_pitch", "head_roll")),
    "right_arm": (
        (11, 12, 13, 14, 15, 16, 17), (-1, -1, 1, 1, 1, 1, -1), (3, 3, 3, 3, 1, 1, 1), ARM
    ),
    "left_arm": (
        (21, 22, 23, 24, 25, 26, 27), (-1, -1, 1, -1, 1, -1, -1), (3, 3, 3, 3, 1, 1, 1), ARM
    ),
}  # fmt: skip
RX1["body"] = tuple(a + b for a, b in zip(RX1["torso"], RX1["head"], strict=True))
ALL_SERVOS = [s for g in ("torso", "head", "right_arm", "left_arm") for s in GROUPS[g]]
# The RX-1 model's arm joint limits (rad), servo order: (lower, upper).
RX1_ARM_LIMITS = {
    "right_arm": (
        (-2.5132, -1.57075, -1.57075, -2.19905, -1.57075, -0.785375, -0.785375),
        (2.5132, 0.50264, 1.57075, 0.0, 1.57075, 0.785375, 0.785375),
    ),
    "left_arm": (
        (-2.5132, -0.50264, -1.57075, -2.19905, -1.57075, -0.785375, -0.785375),
        (2.5132, 1.57075, 1.57075, 0.0, 1.57075, 0.785375, 0.785375),
    ),
}


def _ids(group: str) -> list[int]:
    return [s.id for s in GROUPS[group]]


def _cfg(port: str, group: str = "right_arm", **kwargs) -> FeetechConfig:
    return FeetechConfig(port=port, group=group, **({"reply_timeout_s": REPLY_S} | kwargs))


def _open_sdk_port(path: str) -> _Port:
    port = _Port(path, REPLY_S)  # the SDK's PortHandler with the longer reply timeout
    assert port.setBaudRate(1_000_000)
    return port


def _wait_until(cond, timeout: float = HANG_GUARD_S) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def _new_goals(emu: FeetechEmulator, since: int, n: int) -> list[int]:
    """The next ``n`` goal counts the emulator logs after index ``since`` (a sync write has no
    reply: the emulator may still be handling it when the call returns)."""
    assert _wait_until(lambda: len(emu.goal_log) >= since + n), emu.goal_log[since:]
    return [c for _, _, c in emu.goal_log[since : since + n]]


@pytest.fixture
def emu():
    with FeetechEmulator(_ids("right_arm")) as e:
        yield e


@pytest.fixture
def arm(emu):
    bus = FeetechBus(_cfg(emu.port))
    bus.connect()
    yield bus
    bus.disconnect()


# --- the servo table and conversions ----------------------------------------------------------


@pytest.mark.parametrize("group", sorted(RX1))
def test_table_is_the_rx1_drivers(group):
    ids, directions, gears, joints = RX1[group]
    servos = GROUPS[group]
    assert tuple(s.id for s in servos) == ids
    assert tuple(s.direction for s in servos) == directions
    assert tuple(s.gear for s in servos) == gears
    assert tuple(s.joint for s in servos) == joints


def test_ears_are_listed_but_never_driven():
    assert EAR_SERVO_IDS == (7, 8)
    assert not set(EAR_SERVO_IDS) & set(SERVOS_BY_ID)
    assert sorted(SERVOS_BY_ID) == [1, 2, 3, 4, 5, 6, *range(11, 18), *range(21, 28)]


@pytest.mark.parametrize("servo", ALL_SERVOS, ids=lambda s: f"id{s.id}")
def test_every_servo_follows_the_formula(servo):
    for angle in (-1.0, -0.3, 0.0, 0.1, 0.25, 1.0):
        expected = round(angle / math.pi * 2048 * servo.direction * servo.gear + 2048)
        assert angle_to_counts(angle, servo.direction, servo.gear) == expected


def test_known_counts():
    # Right shoulder pitch (id 11: direction -1, gear 3) at 0.1 rad: 2048 - 195.6.
    assert angle_to_counts(0.1, -1, 3) == 1852
    # Left elbow (id 24: -1, 3) at -pi/6: 2048 + 1024.
    assert angle_to_counts(-math.pi / 6, -1, 3) == 3072
    # Neck yaw (id 4: -1, 1) at pi/2: 2048 - 1024.
    assert angle_to_counts(math.pi / 2, -1, 1) == 1024
    assert counts_to_angle(3072, 1, 3) == pytest.approx(math.pi / 6)
    servos = GROUPS["left_arm"]
    d = [s.direction for s in servos]
    g = [s.gear for s in servos]
    assert angle_to_counts(np.zeros(7), d, g).tolist() == [2048] * 7
    assert np.all(np.signbit(counts_to_angle(np.full(7, 2048), d, g)) == 0)  # no -0.0


_servo = st.sampled_from(ALL_SERVOS)


@given(_servo, st.lists(st.integers(-40_000, 40_000), min_size=1, max_size=16))
def test_counts_round_trip_is_exact(servo, counts):
    c = np.array(counts, dtype=np.int64)
    d, g = servo.direction, servo.gear
    assert np.array_equal(angle_to_counts(counts_to_angle(c, d, g), d, g), c)


@given(_servo, st.lists(st.floats(-4.0, 4.0), min_size=1, max_size=16))
def test_angle_round_trip_within_half_a_count(servo, q):
    a = np.array(q)
    back = counts_to_angle(
        angle_to_counts(a, servo.direction, servo.gear), servo.direction, servo.gear
    )
    half_count = math.pi / (2048 * servo.gear) / 2
    assert np.all(np.abs(back - a) <= half_count + TOL)


@given(st.integers(-32767, 32767))
def test_sign_magnitude_matches_the_sdk_and_the_emulator(value):
    raw = to_sign_magnitude(value)
    assert raw == SCS_TOSCS(value, 15) and 0 <= raw <= 0xFFFF
    assert from_sign_magnitude(raw) == SCS_TOHOST(raw, 15) == value
    assert encode(value, 2, 15) == raw.to_bytes(2, "little")
    assert decode(raw.to_bytes(2, "little"), 15) == value


# --- config -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"port": ""}, "port"),
        ({"group": "tail"}, "group"),
        ({"baudrate": 4_000_000}, "baudrate"),
        ({"joint_names": ("a",)}, "joint_names"),
        ({"joint_names": ("a",) * 7}, "joint_names"),
        ({"lower": (0.0,) * 6}, "lower"),
        ({"upper": (float("inf"),) * 7}, "upper"),
        ({"lower": (1.0,) * 7, "upper": (0.0,) * 7}, "lower"),
        ({"speed_rad_s": 0.0}, "speed_rad_s"),
        ({"speed_rad_s": 2.0}, "speed_rad_s"),  # above 4.71 rad/s / gear 3
        ({"speed_rad_s": float("nan")}, "speed_rad_s"),
        ({"acceleration_rad_s2": 0.01}, "acceleration_rad_s2"),
        ({"acceleration_rad_s2": 20.0}, "acceleration_rad_s2"),
        ({"model_number": -1}, "model_number"),
        ({"timeout_s": 0.0}, "timeout_s"),
        ({"reply_timeout_s": -1.0}, "reply_timeout_s"),
        ({"retries": 11}, "retries"),
        ({"name": ""}, "name"),
    ],
)
def test_config_validation_names_the_field(kwargs, field):
    base = {"port": "/dev/ttyUSB0", "group": "right_arm"} | kwargs
    with pytest.raises(ValueError, match=rf"FeetechConfig\.{field} must"):
        FeetechConfig(**base)


def test_group_message_lists_valid_groups():
    with pytest.raises(ValueError, match=r"\['body', 'head', 'left_arm', 'right_arm', 'torso'\]"):
        FeetechConfig(port="p", group="arm")


def test_config_defaults_and_registers():
    cfg = FeetechConfig(port="p", group="right_arm")
    assert cfg.baudrate == 1_000_000 and cfg.device_name == "rx1_right_arm"
    assert cfg.device_joint_names == ARM
    # 1 rad/s of joint: x gear x 4096 / 2 pi steps/s; 3 rad/s^2: / 100.
    assert cfg.speed_registers().tolist() == [1956] * 4 + [652] * 3
    assert cfg.acceleration_registers().tolist() == [59] * 4 + [20] * 3
    assert cfg.max_velocity == 1.0
    full = FeetechConfig(port="p", group="head", speed_rad_s=None, acceleration_rad_s2=None)
    assert full.speed_registers().tolist() == [0] * 3
    assert full.acceleration_registers().tolist() == [0] * 3
    assert full.max_velocity == pytest.approx(STS3215_NO_LOAD_RAD_S)
    body = FeetechConfig(port="p", group="body", speed_rad_s=None)
    assert body.max_velocity == pytest.approx(STS3215_NO_LOAD_RAD_S / 3)  # the geared torso


def test_count_limits_follow_direction_within_the_multi_turn_range():
    # Right shoulder pitch (-1, 3): model [-0.1, 0.2] -> counts [2048 - 391.2, 2048 + 195.6].
    lower = (-0.1, -3.0, -3.0, -30.0, -3.0, 0.5, 0.3)
    upper = (0.2, 3.0, 3.0, 30.0, 3.0, 0.5 + 1e-6, 0.3)
    cfg = FeetechConfig(port="p", group="right_arm", lower=lower, upper=upper)
    lo, hi = cfg.count_limits()
    assert (lo[0], hi[0]) == (1657, 2243)
    # +-3 rad x gear 3: past one turn both ways (2048 -+ 5867.04), kept: multi-turn.
    assert (lo[1], hi[1]) == (2048 - 5867, 2048 + 5867)
    assert (lo[3], hi[3]) == (-MULTI_TURN_MAX_COUNT, MULTI_TURN_MAX_COUNT)  # +-30 rad: 7 turns
    assert lo[5] == hi[5] == angle_to_counts(0.5, 1, 1)  # narrower than a count: the nearest
    assert lo[6] == hi[6] == angle_to_counts(0.3, -1, 1)
    assert [x.tolist() for x in cfg.limited_count_sides()] == [[True] * 7, [True] * 7]
    free = FeetechConfig(port="p", group="right_arm", upper=upper)
    lo, hi = free.count_limits()
    # No lower limits: shoulder pitch (direction -1) is unbounded above, arm yaw (+1) below.
    assert (lo[0], hi[0]) == (1657, MULTI_TURN_MAX_COUNT)
    assert (lo[2], hi[2]) == (-MULTI_TURN_MAX_COUNT, 2048 + 5867)
    low_known, high_known = free.limited_count_sides()
    assert low_known.tolist() == [True, True, False, False, False, False, True]
    assert high_known.tolist() == [False, False, True, True, True, True, False]


def test_allowed_counts_and_the_rx1_angle_limits():
    assert MULTI_TURN_MAX_COUNT == 7 * 4096
    assert allowed_counts(0, 0) == (-MULTI_TURN_MAX_COUNT, MULTI_TURN_MAX_COUNT)
    assert allowed_counts(0, 4095) == (0, 4095)
    assert allowed_counts(1000, 3000) == (1000, 3000)
    for bad in ((3000, 1000), (0, 4096), (5, 5)):
        with pytest.raises(ValueError, match="multi-turn"):
            allowed_counts(*bad)
    # Multi-turn behind every 3:1 gearbox (Red-Rabbit-Robotics/rx1 issue #3), one turn elsewhere.
    assert sorted(RX1_ANGLE_LIMITS) == sorted(SERVOS_BY_ID)
    for s in ALL_SERVOS:
        assert RX1_ANGLE_LIMITS[s.id] == ((0, 0) if s.gear == 3 else (0, 4095))
    # The whole RX-1 arm range fits in what these limits allow, and in 15-bit sign-magnitude.
    for group, (lower, upper) in RX1_ARM_LIMITS.items():
        lo, hi = FeetechConfig(port="p", group=group, lower=lower, upper=upper).count_limits()
        for k, s in enumerate(GROUPS[group]):
            a_lo, a_hi = allowed_counts(*RX1_ANGLE_LIMITS[s.id])
            assert a_lo <= lo[k] <= hi[k] <= a_hi
            assert -32767 <= lo[k] and hi[k] <= 32767


# --- shared servo model ----------------------------------------------------------------------


def test_servo_model_bounded_speed_ends_on_goal():
    assert step_towards(0.0, 100.0, 0.1, 500.0) == (50.0, 500.0)
    assert step_towards(0.0, -100.0, 0.1, 500.0) == (-50.0, -500.0)
    assert step_towards(90.0, 100.0, 0.1, 500.0) == (100.0, pytest.approx(100.0))
    assert step_towards(5.0, 5.0, 0.1, 500.0) == (5.0, 0.0)


def test_servo_model_accelerates_and_brakes_onto_goal():
    pos, vel, dt, accel, peak = 0.0, 0.0, 0.005, 2000.0, 0.0
    for _ in range(2000):
        new_pos, new_vel = step_towards(pos, 400.0, dt, 1000.0, vel, accel)
        assert abs(new_vel - vel) <= accel * dt + 1e-6 or new_pos == 400.0
        assert new_pos <= 400.0
        pos, vel, peak = new_pos, new_vel, max(peak, new_vel)
        if pos == 400.0:
            break
    assert pos == 400.0
    assert peak < 1000.0  # 400 counts at 2000/s^2 never reach 1000/s: a triangle profile


# --- emulator protocol, through the SDK's own packet code -------------------------------------


class _CapturePort:
    """Just enough of a PortHandler for the SDK's txPacket to write into."""

    is_using = False
    tx_time_per_byte = 0.01

    def __init__(self) -> None:
        self.sent = b""

    def clearPort(self) -> None:
        pass

    def writePort(self, packet) -> int:
        self.sent = bytes(packet)
        return len(packet)

    def setPacketTimeout(self, length) -> None:
        pass


def test_packets_and_checksum_match_sdk():
    ph = PacketHandler(0)
    port = _CapturePort()
    ph.writeTxOnly(port, 12, 42, 2, [0x34, 0x12])
    assert build_packet(12, INST_WRITE, bytes([42, 0x34, 0x12])) == port.sent
    ph.readTx(port, 5, 56, 2)
    assert build_packet(5, INST_READ, bytes([56, 2])) == port.sent
    port.is_using = False  # readTx leaves the port to the reply it waits for
    ph.syncWriteTxOnly(port, 41, 2, [11, 1, 2, 12, 3, 4], 6)
    assert build_packet(0xFE, INST_SYNC_WRITE, bytes([41, 2, 11, 1, 2, 12, 3, 4])) == port.sent
    # The checksum, by its definition: ~(id + length + instruction + params) & 0xFF.
    packet = build_packet(1, INST_WRITE, bytes([40, 1]))
    assert packet == bytes([0xFF, 0xFF, 1, 4, 3, 40, 1, ~(1 + 4 + 3 + 40 + 1) & 0xFF])


@given(st.integers(0, 253), st.integers(0, 255), st.binary(max_size=60))
def test_checksum_matches_sdk(servo_id, instruction, params):
    port = _CapturePort()
    packet = [0] * (len(params) + 6)
    packet[2], packet[3], packet[4] = servo_id, len(params) + 2, instruction
    packet[5 : 5 + len(params)] = list(params)
    assert PacketHandler(0).txPacket(port, packet) == COMM_SUCCESS
    assert build_packet(servo_id, instruction, params) == port.sent
    assert checksum(port.sent[2:-1]) == port.sent[-1]


def test_sdk_ping_read_write_sync_write_sync_read():
    start = {1: 100, 2: 4000, 3: 2048}
    with FeetechEmulator((1, 2, 3), initial_position=start, angle_limits=ONE_TURN) as e:
        port = _open_sdk_port(e.port)
        ph = PacketHandler(0)
        try:
            assert ph.ping(port, 2) == (777, COMM_SUCCESS, 0)
            assert ph.ping(port, 9)[1] != COMM_SUCCESS  # nobody there
            assert ph.read2ByteTxRx(port, 2, 56) == (4000, COMM_SUCCESS, 0)
            assert ph.read1ByteTxRx(port, 1, 33) == (0, COMM_SUCCESS, 0)  # position mode
            assert ph.write1ByteTxRx(port, 3, 40, 1) == (COMM_SUCCESS, 0)
            assert ph.write2ByteTxRx(port, 3, 46, 3000) == (COMM_SUCCESS, 0)
            assert e.servos[3].torque_enable == 1 and e.servos[3].goal_speed == 3000
            assert ph.write1ByteTxRx(port, 3, 40, 0) == (COMM_SUCCESS, 0)
            # A negative goal goes out as sign and magnitude; one-turn limits clamp it to 0.
            assert ph.write2ByteTxRx(port, 3, 42, SCS_TOSCS(-5, 15)) == (COMM_SUCCESS, 0)
            assert e.goal_log[-1][1:] == (3, -5) and e.servos[3].goal_position == 0
            writer = GroupSyncWrite(port, ph, 42, 2)
            for i, c in ((1, 300), (2, 3900)):
                assert writer.addParam(i, list(c.to_bytes(2, "little")))
            assert writer.txPacket() == COMM_SUCCESS
            assert _wait_until(lambda: e.servos[2].goal_position == 3900)
            assert e.servos[1].goal_position == 300
            reader = GroupSyncRead(port, ph, 56, 2)
            for i in start:
                reader.addParam(i)
            assert reader.txRxPacket() == COMM_SUCCESS
            assert {i: reader.getData(i, 56, 2) for i in start} == {1: 100, 2: 4000, 3: 2048}
            assert [inst for _, _, inst in e.packet_log[-2:]] == [0x83, 0x82]
        finally:
            port.closePort()


def test_multi_turn_servo_takes_and_reports_signed_positions_past_one_turn():
    start = {1: -1979, 2: 6964, 3: 2048}
    limits = {1: MULTI_TURN, 2: MULTI_TURN, 3: ONE_TURN}
    with FeetechEmulator((1, 2, 3), initial_position=start, angle_limits=limits) as e:
        port = _open_sdk_port(e.port)
        ph = PacketHandler(0)
        try:
            assert ph.readTxRx(port, 1, 9, 4)[0] == [0, 0, 0, 0]  # multi-turn: limits 0 and 0
            assert ph.readTxRx(port, 3, 9, 4)[0] == [0, 0, 0xFF, 0x0F]
            assert ph.read1ByteTxRx(port, 1, 18)[0] & 0x10  # full-angle feedback
            # Negative present positions come back as sign and magnitude (bit 15).
            assert ph.read2ByteTxRx(port, 1, 56)[0] == 0x8000 | 1979
            assert ph.read2ByteTxRx(port, 2, 56)[0] == 6964
            for i, goal in ((1, -4300), (3, -5)):
                ph.write2ByteTxRx(port, i, 42, to_sign_magnitude(goal))
            assert e.servos[1].goal_position == -4300  # multi-turn: taken as it is
            assert e.servos[3].goal_position == 0  # one turn: clamped
            assert e.servos[1].table()[42:44] == (0x8000 | 4300).to_bytes(2, "little")
            ph.write1ByteTxRx(port, 1, 40, 1)
            assert _wait_until(lambda: e.servos[1].present_position == -4300)
            assert from_sign_magnitude(ph.read2ByteTxRx(port, 1, 56)[0]) == -4300
            # Without full-angle feedback (Phase bit 4) it reports the angle within one turn.
            e.servos[1].phase = 0
            assert ph.read2ByteTxRx(port, 1, 56)[0] == -4300 % 4096 == 3892
        finally:
            port.closePort()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"angle_limits": (3000, 1000)}, "angle_limits"),
        ({"angle_limits": {1: (0, 4096)}}, "angle_limits"),
        ({"angle_limits": ONE_TURN, "initial_position": -1}, "initial_position"),
        ({"initial_position": 40_000}, "initial_position"),
    ],
)
def test_emulator_refuses_limits_and_starts_a_servo_cannot_have(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FeetechEmulator((1, 2), **kwargs)


def test_emulated_servo_moves_with_torque_at_its_goal_speed():
    with FeetechEmulator((1,)) as e:
        port = _open_sdk_port(e.port)
        ph = PacketHandler(0)
        try:
            ph.write2ByteTxRx(port, 1, 46, 2000)  # 2000 steps/s
            ph.write2ByteTxRx(port, 1, 42, 2648)
            e.advance(time.monotonic() + 0.05)  # the servo model runs 50 ms, however loaded
            assert e.servos[1].position == 2048.0  # torque off: goal taken, no motion
            ph.write1ByteTxRx(port, 1, 40, 1)
            t0 = time.monotonic()
            assert _wait_until(lambda: e.servos[1].present_position == 2648)
            assert time.monotonic() - t0 > 0.25  # 600 counts at 2000 steps/s
            assert ph.read2ByteTxRx(port, 1, 56)[0] == 2648
        finally:
            port.closePort()


def test_bad_checksum_gets_no_reply_and_garbage_does_not_crash(emu):
    fd = os.open(emu.port, os.O_RDWR | os.O_NOCTTY)
    try:
        good = build_packet(11, 0x01)
        os.write(fd, good[:-1] + bytes([good[-1] ^ 0xFF]))
        ready, _, _ = select.select([fd], [], [], 0.15)
        assert not ready  # ignored: no status packet
        assert emu.parser.checksum_errors == 1
        rng = random.Random(7)
        noise = bytes(rng.randrange(256) for _ in range(400))
        impossible = b"\xff\xff\x0b\x01\x02"  # length 1
        too_long = b"\xff\xff\x0b\xfa\x02"  # length 250
        partial = b"\xff\xff\x0b\x20\x03\x2a"  # promises 32 bytes, stops
        os.write(fd, noise + impossible + too_long + b"\xff\xff\xff" + noise[:50] + partial)
        # The emulator took it all in and gave up on the partial packet at the end.
        assert _wait_until(lambda: emu.parser.dropped > 0 and not emu.parser.buffer)
        while select.select([fd], [], [], 0)[0]:  # whatever the noise happened to ask
            os.read(fd, 4096)
    finally:
        os.close(fd)
    port = _open_sdk_port(emu.port)
    try:
        assert PacketHandler(0).ping(port, 11) == (777, COMM_SUCCESS, 0)
    finally:
        port.closePort()
    assert emu.faults == [] and emu._thread is not None and emu._thread.is_alive()
    assert emu.parser.dropped > 0


# --- driver -----------------------------------------------------------------------------------


def test_connect_enables_torque_at_the_present_pose():
    start = {i: 1500 + 100 * k for k, i in enumerate(_ids("right_arm"))}
    with FeetechEmulator(list(start), initial_position=start) as e:
        for s in e.servos.values():
            s.goal_position = 3000  # stale, from an earlier session
        with FeetechBus(_cfg(e.port)) as bus:
            assert bus.connected and bus.model_numbers == dict.fromkeys(start, 777)
            cfg = bus.config
            for k, (i, s) in enumerate(e.servos.items()):
                assert s.torque_enable == 1
                assert s.goal_position == start[i]  # goal = present before torque on
                assert s.goal_speed == cfg.speed_registers()[k]
                assert s.acceleration == cfg.acceleration_registers()[k]
                addrs = [a for a, _, _ in s.writes]
                assert addrs[-1] == 40  # torque last
            e.advance(time.monotonic() + 0.05)  # the servo model runs 50 ms, however loaded
            assert all(s.present_position == start[i] for i, s in e.servos.items())
            servos = GROUPS["right_arm"]
            expected = [counts_to_angle(start[s.id], s.direction, s.gear) for s in servos]
            assert bus.read_positions() == pytest.approx(expected)
            assert bus.stream_hz == 100.0 and bus.max_velocity == 1.0
        assert not bus.connected


def test_send_converges_and_goals_are_the_formula():
    with FeetechEmulator(_ids("left_arm")) as e:
        cfg = _cfg(e.port, "left_arm", speed_rad_s=1.5, acceleration_rad_s2=None)
        with FeetechBus(cfg) as bus:
            target = np.array([0.3, -0.2, 0.25, -0.3, 0.4, -0.5, 0.2])
            n = len(e.goal_log)
            sent = bus.send_positions(target)
            half_counts = np.pi / (2048 * cfg.gears) / 2
            assert np.all(np.abs(sent - target) <= half_counts + TOL)
            goals = _new_goals(e, n, 7)
            servos = GROUPS["left_arm"]
            assert goals == [
                round(q / math.pi * 2048 * s.direction * s.gear + 2048)
                for q, s in zip(target, servos, strict=True)
            ]
            assert _wait_until(lambda: np.allclose(bus.read_positions(), sent, atol=1e-12))
            assert bus.commands_sent == 1 and bus.errors == 0


def test_clipping_is_reported_in_the_returned_targets(emu):
    lower, upper = RX1_ARM_LIMITS["right_arm"]
    with FeetechBus(_cfg(emu.port, lower=lower, upper=upper)) as bus:
        # Multi-turn servos: shoulder pitch 2.0 rad (past one servo turn at gear 3, +-pi/3) goes
        # out as it is; the elbow asks past its model limit; the wrist far past it.
        q = np.array([2.0, 0.2, -1.3, 0.4, 0.1, -9.0, 1e300])
        n = len(emu.goal_log)
        sent = bus.send_positions(q)
        goals = _new_goals(emu, n, 7)
        assert goals[0] == round(2048 - 2.0 / math.pi * 2048 * 3) == -1863  # below count 0
        assert goals[2] == round(2048 - 1.3 / math.pi * 2048 * 3) == -494
        assert sent[0] == pytest.approx(2.0, abs=math.pi / 6144)
        assert sent[3] <= 0.0 and sent[3] == pytest.approx(0.0, abs=1e-12)
        assert sent[5] == pytest.approx(-0.785375, abs=math.pi / 2048)
        assert sent[6] == pytest.approx(0.785375, abs=math.pi / 2048)
        assert sent[1] == pytest.approx(0.2, abs=math.pi / 6144)
        servos = GROUPS["right_arm"]
        back = [counts_to_angle(c, s.direction, s.gear) for c, s in zip(goals, servos, strict=True)]
        assert np.array_equal(back, sent)


def test_one_turn_servos_without_model_limits_clip_to_their_turn():
    with FeetechEmulator(_ids("right_arm"), angle_limits=ONE_TURN) as e:
        with FeetechBus(_cfg(e.port)) as bus:  # no model limits: nothing to refuse
            assert bus.angle_limits == dict.fromkeys(_ids("right_arm"), (0, 4095))
            n = len(e.goal_log)
            sent = bus.send_positions(np.array([2.0, 0.0, -1.3, 0.0, 0.0, 0.0, 1e300]))
            goals = _new_goals(e, n, 7)
            assert all(0 <= c <= 4095 for c in goals)
            assert goals[0] == 0 and sent[0] == pytest.approx(math.pi / 3)  # direction -1
            assert goals[2] == 0 and sent[2] == -math.pi / 3  # arm yaw: direction +1
            assert goals[6] == 0 and sent[6] == pytest.approx(math.pi)  # wrist roll: -1, gear 1


@pytest.mark.parametrize("group", ["right_arm", "left_arm"])
def test_rx1_arm_extremes_round_trip_through_multi_turn_servos(group):
    """The shoulder pitch and the elbow at both ends of their model range, negative counts and
    counts past 4095 included, are sent as the formula's counts and read back within a count."""
    lower, upper = RX1_ARM_LIMITS[group]
    ids = _ids(group)
    limits = {i: RX1_ANGLE_LIMITS[i] for i in ids}
    with FeetechEmulator(ids, angle_limits=limits, top_speed_steps=60_000) as e:
        cfg = _cfg(e.port, group, lower=lower, upper=upper, speed_rad_s=None)
        with FeetechBus(cfg) as bus:
            assert bus.angle_limits == limits
            servos = GROUPS[group]
            for end in (lower, upper):
                q = np.zeros(7)
                q[0], q[3] = end[0], end[3]  # shoulder pitch, elbow
                n = len(e.goal_log)
                sent = bus.send_positions(q)
                goals = _new_goals(e, n, 7)
                for k in (0, 3):
                    s = servos[k]
                    exact = q[k] / math.pi * 2048 * s.direction * s.gear + 2048
                    assert abs(goals[k] - exact) < 1.0  # the formula, rounded inward
                    assert abs(sent[k] - q[k]) < math.pi / 2048 / 3
                assert np.array_equal(
                    sent, counts_to_angle(goals, [s.direction for s in servos], cfg.gears)
                )
                assert _wait_until(
                    lambda sent=sent: np.all(np.abs(bus.read_positions() - sent) <= 1e-12)
                )
                raw = [e.servos[i].table()[56:58] for i in ids]
                assert [decode(r, 15) for r in raw] == goals
            # Where the counts went: below 0 and past 4095 (direction and gear 3).
            seen = [c for _, i, c in e.goal_log if i in (ids[0], ids[3])]
            assert min(seen) < -2000 and max(seen) > 6000


def test_negative_goals_and_positions_on_the_wire(emu, arm):
    n = len(emu.goal_log)
    arm.send_positions(np.array([0.0, 0.0, 0.0, -2.0, 0.0, 0.0, 0.0]))  # elbow (+1, 3)
    goal = round(2048 - 2.0 / math.pi * 2048 * 3)
    assert goal == -1863 and _new_goals(emu, n, 7)[3] == goal
    s = emu.servos[14]
    assert s.table()[42:44] == bytes([1863 & 0xFF, 0x80 | 1863 >> 8])  # bit 15: negative
    assert s.goal_position == goal
    assert _wait_until(lambda: s.present_position == goal)
    assert s.table()[56:58] == s.table()[42:44]
    assert arm.read_positions()[3] == pytest.approx(counts_to_angle(goal, 1, 3))
    assert arm.read_positions()[3] == pytest.approx(-2.0, abs=math.pi / 6144)


def test_one_turn_limits_too_narrow_for_the_model_refuse_to_connect():
    lower, upper = RX1_ARM_LIMITS["right_arm"]
    ids = _ids("right_arm")
    # The factory's one turn everywhere, as a servo comes out of the box.
    with FeetechEmulator(ids, angle_limits=ONE_TURN) as e:
        bus = FeetechBus(_cfg(e.port, lower=lower, upper=upper))
        with pytest.raises(DeviceError, match=r"servo\(s\) \[11, 12, 13, 14\] cannot reach") as err:
            bus.connect()
        text = str(err.value)
        for part in (
            "11 shoulder_pitch: needs counts -2867..6963",
            "14 elbow: needs counts -2252..2048",
            "allow 0..4095",
            "set both to 0",
            "multi-turn",
            "Phase (18)",
            "rx1_right_arm",
        ):
            assert part in text
        assert not bus.connected and bus.errors == 1
        assert all(s.torque_enable == 0 and s.writes == [] for s in e.servos.values())
    # The RX-1's own setup connects; so would a gear-1 servo with limits its range fits in.
    limits = {i: RX1_ANGLE_LIMITS[i] for i in ids} | {16: (1000, 3000)}  # wrist pitch: +-0.785
    with FeetechEmulator(ids, angle_limits=limits) as e:
        with FeetechBus(_cfg(e.port, lower=lower, upper=upper)) as bus:
            assert bus.angle_limits == limits
        e.servos[15].min_angle_limit, e.servos[15].max_angle_limit = 1500, 2600  # forearm yaw
        with pytest.raises(DeviceError, match=r"\[15\] .*1025\.\.3071.*\(1500, 2600\)"):
            FeetechBus(_cfg(e.port, lower=lower, upper=upper)).connect()
        e.servos[15].min_angle_limit, e.servos[15].max_angle_limit = 3000, 1000
        with pytest.raises(DeviceError, match=r"servo 15: angle limits 3000\.\.1000 are neither"):
            FeetechBus(_cfg(e.port, lower=lower, upper=upper)).connect()


def test_multi_turn_servo_without_full_angle_feedback_refuses_to_connect():
    ids = _ids("torso")
    with FeetechEmulator(ids) as e:
        e.servos[1].phase = e.servos[3].phase = 0
        bus = FeetechBus(_cfg(e.port, "torso"))
        with pytest.raises(DeviceError, match=r"servo\(s\) \[1, 3\] run multi-turn.*bit 4"):
            bus.connect()
        assert not bus.connected and all(s.writes == [] for s in e.servos.values())
        # A one-turn servo reports within its turn anyway: its phase does not matter.
        for s in e.servos.values():
            s.max_angle_limit = 4095
        with FeetechBus(_cfg(e.port, "torso")) as bus:
            assert bus.angle_limits == dict.fromkeys(ids, (0, 4095))


def test_missing_servo_ids_are_named():
    with FeetechEmulator([i for i in _ids("right_arm") if i not in (13, 16)]) as e:
        # Present servos get the suite's reply timeout (a loaded machine can delay the
        # emulator by tens of ms); the missing ones are given up on once no servo has answered
        # for timeout_s (how long that takes is a timing figure, not checked here).
        bus = FeetechBus(_cfg(e.port, timeout_s=0.3))
        with pytest.raises(DeviceError, match=r"servo id\(s\) \[13, 16\] .*power.*1 Mbaud") as err:
            bus.connect()
        assert e.port in str(err.value) and "rx1_right_arm" in str(err.value)
        assert not bus.connected
        assert all(s.torque_enable == 0 and s.writes == [] for s in e.servos.values())


def test_wrong_model_or_mode_refuses_to_connect():
    with FeetechEmulator(_ids("head")) as e:
        e.servos[5].model_number = 1284  # an SCS0009 at a neck id
        with pytest.raises(DeviceError, match=r"servo id\(s\) \[5\] .*model number.*\[1284\]"):
            FeetechBus(_cfg(e.port, "head")).connect()
        assert all(s.writes == [] for s in e.servos.values())
        with FeetechBus(_cfg(e.port, "head", model_number=None)) as bus:
            assert bus.model_numbers[5] == 1284
        e.servos[6].operating_mode = 3
        writes = [len(s.writes) for s in e.servos.values()]
        with pytest.raises(DeviceError, match=r"servo 6 is in operating mode 3"):
            FeetechBus(_cfg(e.port, "head", model_number=None)).connect()
        assert [len(s.writes) for s in e.servos.values()] == writes  # nothing written


def test_nonexistent_port_and_calls_before_connect():
    bus = FeetechBus(FeetechConfig(port="/dev/does-not-exist-rx1", group="torso"))
    with pytest.raises(DeviceError, match=r"cannot open serial port '/dev/does-not-exist-rx1'"):
        bus.connect()
    assert not bus.connected
    for call in (bus.read_positions, bus.hold, lambda: bus.send_positions(np.zeros(3))):
        with pytest.raises(DeviceError, match="not connected"):
            call()
    bus.disconnect()


def test_vanished_port_raises_device_error_quickly(emu, arm):
    arm.send_positions(np.zeros(7))
    emu.vanish()
    for call in (lambda: arm.send_positions(np.full(7, 0.1)), arm.read_positions, arm.hold):
        # Quickly: the port's own failure, at once - not a reply waited out and asked again.
        with pytest.raises(DeviceError, match=rf"serial port '{re.escape(emu.port)}' failed while"):
            call()
        assert arm.retries == 0
    assert arm.errors == 3 and arm.commands_sent == 1
    arm.disconnect()
    arm.disconnect()
    assert not arm.connected


@pytest.mark.parametrize("retries", [0, 1])
def test_a_lost_reply_is_retried(emu, retries):
    with FeetechBus(_cfg(emu.port, retries=retries)) as bus:
        emu.drop_replies(1)
        if retries:
            assert bus.read_positions().shape == (7,)
        else:
            with pytest.raises(DeviceError, match=r"no present position from servo 11"):
                bus.read_positions()
        assert (bus.retries, bus.errors) == (retries, 1 - retries)
        emu.drop_replies(0)
        assert bus.read_positions().shape == (7,)


def test_servo_error_byte_raises_device_error(emu, arm):
    emu.inject_error(14, ERRBIT_OVERLOAD)
    with pytest.raises(DeviceError, match=r"servo 14 reports .*Overload"):
        arm.read_positions()
    emu.inject_error(14, 0)
    assert arm.read_positions().shape == (7,)


@pytest.mark.parametrize("bad", [np.full(7, np.nan), np.zeros(6), [np.inf] + [0.0] * 6])
def test_bad_targets_raise_value_error_and_send_nothing(emu, arm, bad):
    before = len(emu.goal_log)
    with pytest.raises(ValueError, match="rx1_right_arm"):
        arm.send_positions(bad)
    arm.read_positions()  # a round trip: whatever went out before it has been handled
    assert len(emu.goal_log) == before and arm.commands_sent == 0


def test_hold_resends_last_target_or_measured_pose():
    ids = _ids("torso")
    start = {1: 2000, 2: 2100, 3: 2200}
    with FeetechEmulator(ids, initial_position=start) as e, FeetechBus(_cfg(e.port, "torso")) as b:
        n = len(e.goal_log)
        b.hold()
        assert b.holding and _new_goals(e, n, 3) == [2000, 2100, 2200]
        sent = b.send_positions(np.array([0.1, -0.1, 0.05]))
        assert not b.holding
        n = len(e.goal_log)
        b.hold()
        assert b.holding and np.array_equal(b.last_target, sent)
        servos = GROUPS["torso"]
        expected = [
            int(angle_to_counts(q, s.direction, s.gear)) for q, s in zip(sent, servos, strict=True)
        ]
        assert _new_goals(e, n, 3) == expected


@pytest.mark.parametrize("torque_off", [False, True])
def test_disconnect_keeps_torque_unless_asked(emu, torque_off):
    bus = FeetechBus(_cfg(emu.port, torque_off_on_disconnect=torque_off))
    bus.connect()
    bus.disconnect()
    bus.disconnect()
    assert all(s.torque_enable == (0 if torque_off else 1) for s in emu.servos.values())


def test_body_group_drives_torso_then_head():
    ids = _ids("body")
    assert ids == [1, 2, 3, 4, 5, 6]
    names = tuple(f"body/{s.joint}" for s in GROUPS["body"])
    with FeetechEmulator(ids) as e, FeetechBus(_cfg(e.port, "body", joint_names=names)) as b:
        assert b.joint_names[0] == "body/torso_yaw" and b.joint_names[-1] == "body/head_roll"
        n = len(e.goal_log)
        b.send_positions(np.full(6, 0.2))
        # Torso: gear 3; head: gear 1; directions -1, 1, -1, -1, -1, -1.
        g = 0.2 / math.pi * 2048
        assert _new_goals(e, n, 6) == [round(2048 + s * g) for s in (-3, 3, -3, -1, -1, -1)]


# --- property: nothing outside the limits ever reaches the bus --------------------------------

_RNG = np.random.default_rng(5)
_LOWER = tuple(float(x) for x in _RNG.uniform(-2.0, 0.0, 7))
_UPPER = tuple(float(x) for x in _RNG.uniform(0.05, 2.0, 7))


@pytest.fixture(scope="module")
def limited():
    with FeetechEmulator(_ids("left_arm")) as e:
        bus = FeetechBus(_cfg(e.port, "left_arm", lower=_LOWER, upper=_UPPER))
        bus.connect()
        yield e, bus
        bus.disconnect()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-50.0, 50.0), min_size=7, max_size=7))
def test_every_goal_received_lies_within_the_limits(limited, q):
    e, bus = limited
    n = len(e.goal_log)
    sent = bus.send_positions(np.array(q))
    counts = _new_goals(e, n, 7)
    assert [i for _, i, _ in e.goal_log[n:]] == _ids("left_arm")
    assert all(-MULTI_TURN_MAX_COUNT <= c <= MULTI_TURN_MAX_COUNT for c in counts)
    servos = GROUPS["left_arm"]
    angles = np.array(
        [counts_to_angle(c, s.direction, s.gear) for c, s in zip(counts, servos, strict=True)]
    )
    assert np.all(angles >= np.array(_LOWER) - 1e-9) and np.all(angles <= np.array(_UPPER) + 1e-9)
    assert np.array_equal(angles, sent)


# --- the emulator process ---------------------------------------------------------------------


def test_emulators_process_reports_sync_writes_in_model_radians():
    start = [2048, 2100, 1900]
    # The right arm starts at the RX-1's elbow home, -2.06 rad: a count below 0, multi-turn.
    arm_start = [2048, 2048, 2048, int(angle_to_counts(-2.0595, 1, 3)), 2048, 2048, 2048]
    plan = [
        ["torso", "feetech", {"group": "torso", "counts": start}],
        ["right", "feetech", {"group": "right_arm", "counts": arm_start}],
    ]
    proc = subprocess.Popen(
        [sys.executable, "-m", "beavr_sim.hardware.emulators", json.dumps(plan)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        where = json.loads(proc.stdout.readline())
        with FeetechBus(_cfg(where["torso"], "torso")) as bus:
            measured = bus.read_positions()
            sent = bus.send_positions(np.array([0.1, 0.0, -0.05]))
        lower, upper = RX1_ARM_LIMITS["right_arm"]
        with FeetechBus(_cfg(where["right"], lower=lower, upper=upper)) as arm:
            assert arm.angle_limits == {i: RX1_ANGLE_LIMITS[i] for i in _ids("right_arm")}
            assert arm_start[3] == -1980
            assert arm.read_positions()[3] == pytest.approx(-2.0595, abs=math.pi / 6144)
        proc.stdin.write("close\n")
        proc.stdin.flush()
        received = json.loads(proc.stdout.readline())["torso"]
        assert len(where) == 2
        assert proc.wait(10.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    servos = GROUPS["torso"]
    expected = [counts_to_angle(c, s.direction, s.gear) for c, s in zip(start, servos, strict=True)]
    assert measured == pytest.approx(expected)
    assert len(received) == 2  # connect's goal = present, then one send
    assert received[0][1] == pytest.approx({"1": expected[0], "2": expected[1], "3": expected[2]})
    assert received[1][1] == pytest.approx({"1": sent[0], "2": sent[1], "3": sent[2]}, abs=1e-12)
