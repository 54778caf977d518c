"""The LEAP hand driver: 16 Dynamixel X-series motors over Protocol 2.0, via ``dynamixel_sdk``.

Joint order is motor-id order (index 0-3, middle 4-7, ring 8-11, thumb 12-15). The units
(model angle + pi = motor angle, 4096 counts a turn) are :mod:`beavr_sim.hardware.leap.config`'s;
the port, ping, retries and sync read and write are :class:`~beavr_sim.hardware.serial_bus.SerialBus`'s.

Set-up follows the LEAP hand's published API (leap-hand/LEAP_Hand_API): current-based position
mode (5), position gains P 600 / I 0 / D 200 with 0.75x P and D on the side-to-side motors 0, 4
and 8, and the current limit written to Goal Current (102): 550 mA for the full hand, 350 mA
for the Lite. Targets are clipped to the model's joint limits (as LEAP clips to its limits
before writing) and to one motor turn, then sent in one sync write of Goal Position (116);
positions come back in one sync read of Present Position (132).

Notes on ``dynamixel-sdk`` 4.1.0, from its source: ``GroupSyncRead.txRxPacket`` sends the plain
sync read (0x82; fast sync read 0x8A only through ``fastSyncRead``) and drops each status
packet's error byte, so reads go out through the group and the replies come back through
``PacketHandler.readRx``, which keeps it; ``txPacket`` discards the result of its own byte
stuffing, so instruction packets go out unstuffed (harmless here: goals within 0..4095 never
hold FF FF FD); replies are busy-polled against a timeout of about 34 ms (our port waits in
``select`` instead: :class:`~beavr_sim.hardware.serial_bus.ReplyTimeoutPort`), which
``reply_timeout_s`` can replace, and a lost or corrupt reply is asked for again ``retries``
times.

Tested only against :mod:`beavr_sim.hardware.leap.emulator` through the real SDK; nothing here
has run on a real LEAP hand.
"""

from __future__ import annotations

import dynamixel_sdk
import numpy as np
from dynamixel_sdk import PacketHandler, PortHandler

from beavr_sim.hardware.leap.config import (
    ADDR_GOAL_CURRENT,
    ADDR_GOAL_POSITION,
    ADDR_OPERATING_MODE,
    ADDR_POSITION_D,
    ADDR_POSITION_I,
    ADDR_POSITION_P,
    ADDR_PRESENT_POSITION,
    ADDR_TORQUE_ENABLE,
    CURRENT_BASED_POSITION_MODE,
    MAX_COUNT,
    RAD_PER_COUNT,
    LeapHandConfig,
    counts_to_model,
    hardware_to_counts,
    model_to_counts,
    model_to_hardware,
)
from beavr_sim.hardware.serial_bus import BusText, ReplyTimeoutPort, SerialBus


class _Port(ReplyTimeoutPort, PortHandler):
    """The SDK's PortHandler with the reply timeout taken from the config."""


class LeapHand(SerialBus):
    """One LEAP hand on a U2D2 serial adapter. See the module docstring."""

    sdk = dynamixel_sdk
    port_class = _Port
    text = BusText(
        unit="motor",
        adapter="the U2D2 adapter",
        power="the hand's power supply",
        cable="the USB cable",
    )
    torque_address = ADDR_TORQUE_ENABLE
    position_block = (ADDR_PRESENT_POSITION, 4)
    goal_block = (ADDR_GOAL_POSITION, 4)

    def __init__(self, config: LeapHandConfig) -> None:
        super().__init__(config, config.motor_ids)
        self.name = config.name
        self.joint_names = config.joint_names or tuple(f"leap_{i}" for i in config.motor_ids)
        self._lo_counts, self._hi_counts = config.count_limits()

    def _packet_handler(self) -> PacketHandler:
        return PacketHandler(2.0)

    def _set_up(self) -> None:
        cfg = self.config
        for i in cfg.motor_ids:
            self._write_register(i, ADDR_TORQUE_ENABLE, 1, 0, "torque enable")
            self._write_register(
                i, ADDR_OPERATING_MODE, 1, CURRENT_BASED_POSITION_MODE, "operating mode"
            )
            p, i_gain, d = cfg.gains(i)
            self._write_register(i, ADDR_POSITION_P, 2, p, "position P gain")
            self._write_register(i, ADDR_POSITION_I, 2, i_gain, "position I gain")
            self._write_register(i, ADDR_POSITION_D, 2, d, "position D gain")
            self._write_register(i, ADDR_GOAL_CURRENT, 2, cfg.goal_current_ma, "goal current (mA)")
        # Goal = present before torque on, so a stale goal from an earlier session cannot make
        # the hand jump.
        self._write_goal_counts(self._read_counts(), count=False)
        for i in cfg.motor_ids:
            self._write_register(i, ADDR_TORQUE_ENABLE, 1, 1, "torque enable")

    def _to_model(self, counts: np.ndarray) -> np.ndarray:
        return counts_to_model(counts)

    def _to_counts(self, q: np.ndarray) -> np.ndarray:
        # Clip in radians first (no int overflow for huge targets), then to whole counts.
        h = np.clip(model_to_hardware(q), 0.0, MAX_COUNT * RAD_PER_COUNT)
        return np.clip(hardware_to_counts(h), self._lo_counts, self._hi_counts)

    def _goal_counts_of(self, q: np.ndarray) -> np.ndarray:
        return model_to_counts(q)

    def _decode_position(self, data: bytes) -> int:
        return int.from_bytes(data, "little", signed=True)

    def _goal_bytes(self, k: int, counts: int) -> bytes:
        return (counts & 0xFFFFFFFF).to_bytes(4, "little")

    def _status_error_text(self, servo_id: int, error: int) -> str:
        return (
            f"motor {servo_id} reports {self._error_text(error)} (status error 0x{error:02x}); "
            f"read Hardware Error Status (70) and reboot the motor"
        )
