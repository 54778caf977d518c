"""Transient faults through the vendors' SDKs against the emulators: retried, ridden out,
reconnected, or a one-line DeviceError. Every fault is injected (``beavr_sim.hardware.faults``)
and starts at the device's next request, so no test depends on how fast the machine is; the
emulators' random draws are seeded by the device name, so every run is the same run."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import beavr_sim.envs  # noqa: F401  (registers the envs)
from beavr_sim.hardware.device import DeviceError
from beavr_sim.hardware.faults import (
    FAULT_KINDS,
    Fate,
    FaultSpec,
    FaultState,
    Verdict,
    parse_fault_specs,
)
from beavr_sim.hardware.feetech.config import GROUPS, FeetechConfig
from beavr_sim.hardware.feetech.driver import FeetechBus
from beavr_sim.hardware.feetech.emulator import FeetechEmulator
from beavr_sim.hardware.leap.config import LeapHandConfig, counts_to_model, model_to_counts
from beavr_sim.hardware.leap.driver import LeapHand
from beavr_sim.hardware.leap.emulator import DynamixelEmulator
from beavr_sim.hardware.rig import EmulatedRig, build_device, emulated_device_names
from beavr_sim.hardware.xarm.config import XArmConfig
from beavr_sim.hardware.xarm.driver import XArm7
from beavr_sim.hardware.xarm.emulator import XArmEmulator

REPLY_S = 0.25  # the emulators share two slow CPUs with the test: replies are given time
NAMES = ("right_arm", "right_hand", "body")
RIGHT_ARM_IDS = [s.id for s in GROUPS["right_arm"]]


# --- the fault syntax ----------------------------------------------------------------------------


def test_fault_specs_parse_and_print_back():
    text = "right_arm:freeze=2.5@10,right_hand:drop=0.05, body:delay_ms=20,right_arm:disconnect@30"
    specs = parse_fault_specs(text, NAMES)
    assert specs == (
        FaultSpec("right_arm", "freeze", 2.5, 10.0),
        FaultSpec("right_hand", "drop", 0.05),
        FaultSpec("body", "delay_ms", 20.0),
        FaultSpec("right_arm", "disconnect", 0.0, 30.0),
    )
    assert ",".join(str(s) for s in specs) == text.replace(" ", "")
    assert parse_fault_specs("", NAMES) == ()


@pytest.mark.parametrize(
    "part, why",
    [
        ("left_arm:freeze=1", "unknown device 'left_arm'"),
        ("right_arm:melt=1", "unknown kind 'melt'"),
        ("freeze=1", "no DEVICE"),
        ("right_arm:freeze", "freeze needs a value"),
        ("right_arm:freeze=soon", "'soon' is not a number"),
        ("right_arm:drop=1.5", "fraction in 0..1"),
        ("right_arm:disconnect=3", "disconnect takes no value"),
        ("right_arm:freeze=1@later", "'later' is not a time"),
        ("right_arm:delay_ms=-5", ">= 0"),
    ],
)
def test_a_bad_fault_names_the_part_the_kinds_and_the_devices(part, why):
    with pytest.raises(ValueError) as err:
        parse_fault_specs(f"right_hand:drop=0.1,{part}", NAMES)
    message = str(err.value)
    assert why in message and repr(part) in message and "\n" not in message
    assert str(list(FAULT_KINDS)) in message and str(list(NAMES)) in message


def test_fault_state_starts_a_fault_at_the_next_request_or_at_its_time():
    state = FaultState("right_arm")
    state.add(FaultSpec("right_arm", "freeze", 2.0), now=0.0)
    assert state.disconnected(now=100.0) is False
    assert state.admit(now=100.0) is Verdict.LOSE  # the freeze starts with this request
    assert state.admit(now=101.9) is Verdict.LOSE
    assert state.admit(now=102.1) is Verdict.SERVE
    state.add(FaultSpec("right_arm", "freeze", 5.0, at_s=1.0), now=200.0)
    assert state.admit(now=200.5) is Verdict.SERVE
    assert state.admit(now=201.5) is Verdict.LOSE
    state.add(FaultSpec("right_arm", "freeze", 0.0), now=202.0)  # ends it at the next request
    assert state.admit(now=202.0) is Verdict.SERVE
    state.add(FaultSpec("right_arm", "disconnect", at_s=3.0), now=300.0)
    assert state.admit(now=302.0) is Verdict.SERVE
    assert state.admit(now=303.0) is Verdict.DISCONNECTED
    assert state.admit(now=1e9) is Verdict.DISCONNECTED  # for good
    assert state.lost == 5


def test_fault_state_drops_and_corrupts_the_fraction_asked_for():
    state = FaultState("right_hand")
    state.add(FaultSpec("right_hand", "drop", 0.25, at_s=0.0))
    fates = [state.fate() for _ in range(4000)]
    assert fates.count(Fate.DROP) == state.dropped
    assert 800 < state.dropped < 1200
    state.add(FaultSpec("right_hand", "drop", 0.0, at_s=0.0))
    state.add(FaultSpec("right_hand", "corrupt", 1.0, at_s=0.0))
    assert {state.fate() for _ in range(10)} == {Fate.CORRUPT}


# --- the serial buses (LEAP on dynamixel_sdk, RX-1 on scservo_sdk) ---------------------------------


def _leap():
    emulator = DynamixelEmulator(name="right_hand").start()
    config = LeapHandConfig(emulator.port, reply_timeout_s=REPLY_S, timeout_s=0.5)
    return emulator, LeapHand(config)


def _feetech():
    emulator = FeetechEmulator(RIGHT_ARM_IDS, name="right_arm").start()
    config = FeetechConfig(emulator.port, "right_arm", reply_timeout_s=REPLY_S, timeout_s=0.5)
    return emulator, FeetechBus(config)


@pytest.fixture(params=["leap", "feetech"])
def bus(request):
    emulator, device = {"leap": _leap, "feetech": _feetech}[request.param]()
    try:
        device.connect()
        yield emulator, device
    finally:
        device.disconnect()
        emulator.close()


def _true_pose(emulator, device) -> np.ndarray:
    """The joints as the emulated servos hold them (model radians)."""
    with emulator.lock:
        servos = getattr(emulator, "motors", None) or emulator.servos
        counts = np.array([servos[i].present_position for i in device._ids])
    return device._to_model(counts)


def _session(device, n: int = 40, step: float = 0.01) -> None:
    """A stream of targets around the pose, each followed by a read (a mirror's tick)."""
    q0 = device.read_positions()
    for k in range(n):
        device.send_positions(q0 + step * np.sin(k / 5.0))
        device.read_positions()


@pytest.mark.parametrize("kind", ["drop", "corrupt"])
def test_lost_and_garbled_replies_are_retried_and_counted(bus, kind):
    emulator, device = bus
    emulator.inject(FaultSpec(device.name, kind, 0.1))
    _session(device)
    counted = emulator.fault_state.dropped if kind == "drop" else emulator.fault_state.corrupted
    assert counted > 0, "no reply was hit: the test did not test the retry"
    assert device.retries >= counted and device.errors == 0


def test_a_freeze_shorter_than_the_retries_is_ridden_out(bus):
    emulator, device = bus
    emulator.inject(FaultSpec(device.name, "freeze", 0.1))  # from the next request on
    q = device.read_positions()  # the first try meets the freeze, a retry gets through
    assert device.retries >= 1 and device.errors == 0 and emulator.fault_state.lost >= 1
    np.testing.assert_allclose(q, _true_pose(emulator, device))


def test_an_empty_read_is_retried_and_one_that_persists_fails_in_one_line(bus, monkeypatch):
    """pyserial's "ready to read but returned no data" (CI met it once at a LEAP's connect, on
    the emulator's pty): a register request and a ping ask again; an unplugged port keeps
    raising it, and that fails as a port failure in one line once the retries are spent."""
    import serial

    _, device = bus
    handler = type(device._port)
    real_read = handler.readPort
    left = [1]

    def read(self, length):
        if left[0] > 0:
            left[0] -= 1
            raise serial.SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        return real_read(self, length)

    monkeypatch.setattr(handler, "readPort", read)
    servo = device._ids[0]
    torque = device._read_register(servo, device.torque_address, 1, "torque enable")
    assert torque == b"\x01" and device.retries == 1 and device.errors == 0 and left == [0]
    left[0] = 1000  # every read: the port is gone
    with pytest.raises(DeviceError, match="failed while reading torque enable: device reports"):
        device._read_register(servo, device.torque_address, 1, "torque enable")
    assert device.retries == 1 + device.config.retries and device.errors == 1
    left[0] = 1  # a ping that meets one (connect, reconnect) pings again
    device.reconnect()
    assert device.connected and left == [0] and device.errors == 1


def test_a_long_freeze_fails_in_one_line_then_reconnect_reads_the_pose(bus):
    emulator, device = bus
    target = device.read_positions() + 0.05
    sent = device.send_positions(target)
    emulator.inject(FaultSpec(device.name, "freeze", 600.0))
    with pytest.raises(DeviceError) as err:
        device.read_positions()
    assert device.name in str(err.value) and "\n" not in str(err.value)
    assert device.retries == device.config.retries
    with pytest.raises(DeviceError, match="did not answer a ping") as err:
        device.reconnect()  # still frozen
    assert "\n" not in str(err.value) and not device.connected
    emulator.inject(FaultSpec(device.name, "freeze", 0.0))  # it answers again
    q = device.reconnect()
    assert device.connected
    np.testing.assert_allclose(q, _true_pose(emulator, device))
    # The servos kept their torque and their goal: the driver keeps the last target too.
    np.testing.assert_allclose(device.last_target, sent)
    device.hold()
    device.send_positions(q)
    assert device.errors == 2


def test_a_disconnected_bus_fails_reconnect_in_one_line_every_time(bus):
    emulator, device = bus
    emulator.inject(FaultSpec(device.name, "disconnect"))
    with pytest.raises(DeviceError):
        device.read_positions()
    for _ in range(2):
        with pytest.raises(DeviceError, match=rf"{device.name}: .*did not answer a ping") as err:
            device.reconnect()
        assert "\n" not in str(err.value) and not device.connected


def test_late_replies_are_waited_for(bus):
    emulator, device = bus
    emulator.inject(FaultSpec(device.name, "delay_ms", 20.0))
    _session(device, n=5)
    assert device.errors == 0


def test_a_bus_that_stalls_during_the_connect_ping_is_waited_for():
    """A bus whose first answers come late (a busy machine, a slow adapter) is waited for as
    long as some servo answers within ``timeout_s``: the ping does not share one deadline."""
    with FeetechEmulator(RIGHT_ARM_IDS, name="right_arm") as emulator:
        # Ids 11-14 meet the stall (four reply windows, past timeout_s), 15-17 answer.
        emulator.inject(FaultSpec("right_arm", "freeze", 3.5 * REPLY_S))
        config = FeetechConfig(emulator.port, "right_arm", reply_timeout_s=REPLY_S, timeout_s=0.5)
        with FeetechBus(config) as device:
            assert device.connected
            assert sorted(device.model_numbers) == RIGHT_ARM_IDS
        assert emulator.fault_state.lost >= 3


# --- the xArm (xarm-python-sdk over TCP) --------------------------------------------------------


@pytest.fixture
def arm():
    emulator = XArmEmulator(name="right_arm")
    config = XArmConfig(
        host=emulator.host, port=emulator.port, connect_timeout_s=5.0, command_timeout_s=0.5
    )
    device = XArm7(config, name="right_arm")
    try:
        device.connect()
        yield emulator, device
    finally:
        device.disconnect()
        emulator.kill()


@pytest.mark.parametrize("kind", ["drop", "corrupt"])
def test_arm_lost_and_garbled_replies_are_retried_and_counted(arm, kind):
    emulator, device = arm
    emulator.inject(FaultSpec("right_arm", kind, 0.1))
    _session(device, n=30, step=0.002)  # within the controller's speed check
    counted = emulator.fault_state.dropped if kind == "drop" else emulator.fault_state.corrupted
    assert counted > 0, "no reply was hit: the test did not test the retry"
    assert device.retries == counted and device.errors == 0


def test_arm_freeze_shorter_than_the_retries_is_ridden_out(arm):
    emulator, device = arm
    emulator.inject(FaultSpec("right_arm", "freeze", 0.1))
    np.testing.assert_allclose(device.read_positions(), emulator.joints, atol=1e-6)
    assert device.retries >= 1 and device.errors == 0


def test_arm_long_freeze_fails_then_reconnect_restarts_servo_mode(arm):
    emulator, device = arm
    emulator.inject(FaultSpec("right_arm", "freeze", 600.0))
    with pytest.raises(DeviceError, match=r"get_servo_angle failed.*no reply in time") as err:
        device.read_positions()
    assert "\n" not in str(err.value) and device.retries == device.config.retries
    with pytest.raises(DeviceError) as err:
        device.reconnect()  # still frozen: fails within about command_timeout_s
    assert "right_arm (xArm7 at" in str(err.value) and "\n" not in str(err.value)
    emulator.inject(FaultSpec("right_arm", "freeze", 0.0))
    q = device.reconnect()
    np.testing.assert_allclose(q, emulator.joints, atol=1e-6)
    assert emulator.mode == 1 and emulator.state in (1, 2)  # servo mode, started
    sent = device.send_positions(q)
    np.testing.assert_allclose(sent, q, atol=1e-6)


def test_arm_disconnect_fails_reconnect_in_one_line(arm):
    emulator, device = arm
    emulator.inject(FaultSpec("right_arm", "disconnect"))
    with pytest.raises(DeviceError):
        device.read_positions()
    for _ in range(2):
        with pytest.raises(DeviceError, match="cannot connect") as err:
            device.reconnect()
        assert "\n" not in str(err.value)


# --- the emulated rig (the emulators' child process) ---------------------------------------------


def test_emulated_rig_takes_faults_at_start_and_at_run_time():
    env = gym.make("beavr_sim/PickPlace-v0", embodiment="xarm7_leap_right").unwrapped
    with pytest.raises(ValueError, match=r"unknown device 'left_hand'.*devices \['right_arm'"):
        EmulatedRig(env.embodiment, env.joints, faults="left_hand:drop=0.1")
    # as a session builds it: the fault counts read back at close, not the received targets
    rig = EmulatedRig(
        env.embodiment, env.joints, faults="right_arm:disconnect", keep_received=False
    )
    try:
        assert rig.device_names == ("right_arm", "right_hand")
        arm_entry, hand_entry = rig.config.devices
        arm = build_device(arm_entry, env.embodiment, env.joints)
        with pytest.raises(DeviceError, match="right_arm"):
            arm.connect()  # disconnected at its first request
        hand = build_device(hand_entry, env.embodiment, env.joints)
        hand.connect()
        assert rig.inject("right_hand", "freeze=600") == FaultSpec("right_hand", "freeze", 600.0)
        with pytest.raises(DeviceError, match="no present position"):
            hand.read_positions()
        with pytest.raises(DeviceError):
            hand.reconnect()
        rig.inject("right_hand", FaultSpec("right_hand", "freeze", 0.0))
        q = hand.reconnect()
        home_hand = env.joints.home[env.joints.slices["right"]][7:]  # where the rig started it
        np.testing.assert_allclose(q, counts_to_model(model_to_counts(home_hand)))
        with pytest.raises(ValueError, match="unknown kind 'melt'"):
            rig.inject("right_hand", "melt=1")
        with pytest.raises(ValueError, match="not one of device 'right_arm'"):
            rig.inject("right_arm", FaultSpec("right_hand", "drop", 0.1))
        hand.disconnect()
    finally:
        rig.close()
        env.close()
    with pytest.raises(RuntimeError, match="emulators are gone"):
        rig.inject("right_hand", "drop=0.1")
    assert rig.received == {}  # nothing read back (a long session's logs are large)
    assert rig.fault_counts["right_arm"]["lost"] >= 1  # the request that met the disconnect
    assert rig.fault_counts["right_hand"]["lost"] >= 3  # the read and its retries, frozen
    assert emulated_device_names(env.embodiment) == rig.device_names


def test_the_emulator_process_keeps_only_recent_logs():
    """The ``--hardware-config emulated`` child bounds what it keeps of each emulator's logs
    (a rehearsal of hours must not grow without end): at least the limit, at most twice it."""
    from beavr_sim.hardware.emulators import RecentLog

    log = RecentLog(10)
    for k in range(95):
        log.append(k)
        assert len(log) < 20
    assert log[-1] == 94 and len(log) >= 10 and log.dropped == 95 - len(log)
    assert list(log) == list(range(95 - len(log), 95))


def test_the_emulator_process_bounds_every_log_that_grows():
    """Every list an emulator (or one of its motors) appends to while it runs is bounded in the
    ``--hardware-config emulated`` child: each motor's record of register writes grew ~470 MB an
    hour in a mirrored soak when only the emulators' own logs were bounded."""
    from beavr_sim.hardware.emulators import RecentLog, _bound_logs, _motors
    from beavr_sim.hardware.feetech.emulator import FeetechEmulator
    from beavr_sim.hardware.leap.emulator import DynamixelEmulator
    from beavr_sim.hardware.xarm.emulator import XArmEmulator

    #: plain lists that do not grow with running time, and why
    fixed = {"_conns": "one per client connection", "crc_errors": "cleared every packet"}
    emulators = [
        DynamixelEmulator(initial_position=dict.fromkeys(range(16), 2048)),
        FeetechEmulator([1, 2]),
        XArmEmulator(),
    ]
    unbounded = []
    try:
        for emulator in emulators:
            _bound_logs(emulator)
            owners = [emulator, *_motors(emulator)]
            owners += [p for p in (getattr(emulator, "parser", None),) if p is not None]
            assert len(owners) > 1 or isinstance(emulator, XArmEmulator)
            for owner in owners:
                for name, value in vars(owner).items():
                    if isinstance(value, list) and not isinstance(value, RecentLog):
                        if name not in fixed:
                            unbounded.append(f"{type(owner).__name__}.{name}")
    finally:
        for emulator in emulators:
            close = getattr(emulator, "close", None)
            if close is not None:
                close()
    assert not unbounded, f"unbounded in the emulator child: {unbounded}"
