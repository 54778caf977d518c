"""The RX-1 humanoid's Feetech STS3215 bus driver, via the vendor SDK ``scservo_sdk``.

One :class:`FeetechBus` drives one group of the RX-1's servos (``GROUPS``: ``torso``,
``head``, ``body`` = torso then head, ``right_arm``, ``left_arm``) on one serial adapter at
1 Mbaud, in the model's joint convention (radians). The servo table (id, direction, gear, model
joint) and the conversion ``counts = angle / pi * 2048 * direction * gear + 2048`` follow the
RX-1's own ROS driver (Red-Rabbit-Robotics/rx1, ``rx1_motor``) and live in
:mod:`beavr_sim.hardware.feetech.config`, in one tested place; the port, ping, retries and sync
read and write are :class:`~beavr_sim.hardware.serial_bus.SerialBus`'s. Two departures from that
driver: it divides by 3.14, not pi (0.05 % more counts per radian: about 2.5 counts at the
shoulder's +-2.51 rad), and truncates to an integer where this rounds.

Multi-turn: a joint behind a 3:1 gearbox covers only +-pi/3 rad in one servo turn (counts
0..4095), less than its model range (shoulder pitch +-2.51 rad: counts 2048 -+ 4916; elbow
[-2.2, 0] rad: down to 2048 - 4300). The RX-1 driver writes the formula's counts as they come,
negative ones sign-magnitude (bit 15), which works because its makers set both angle limits
(Min 9, Max 11) of every geared servo to 0 (Red-Rabbit-Robotics/rx1 issue #3): the STS3215's
multi-turn position operation ("0 when multi-turn absolute position control is used", its memory
table). ``RX1_ANGLE_LIMITS`` records that setup. Goals here are the formula's counts, clipped
to the model limits and to what each servo's angle limits allow (``allowed_counts``): one
turn, min..max, when they are set; +-7 turns (:data:`MULTI_TURN_MAX_COUNT`) when both are 0.
:meth:`FeetechBus.connect` reads every servo's angle limits and refuses (``DeviceError``, naming
the servos, the joints and the fix) a group whose model joint range does not fit in what its
servos allow, rather than clip the joints there: a clipped joint would hold short of where the
twin goes, every time, where one fix of two EEPROM registers makes it reach. It also refuses a
multi-turn servo whose Phase (18) lacks bit 4 (full-angle feedback): such a servo reports its
position within one turn, so the driver could not tell where the joint is (and "goal = present"
at connect would move it by whole servo turns). Not detectable here: an STS3215 is reported to
forget its turn count when powered off (Red-Rabbit-Robotics/rx1 issue #8), after which it reads
its angle within one turn; power the RX-1 on with its geared joints within one servo turn of
their zero (+-pi/3 rad at a 3:1 joint), or its readings and goals are off by whole turns.

Not modelled: the RX-1's torso pitch and roll servos (ids 2 and 3) form a parallel linkage; its
driver turns (pitch, roll) into the two servo angles with a closed-form IK (``torsoIk``) before
the conversion above (its two callers pass the two torso angles in opposite orders). Here ids 2
and 3 map one-to-one to ``torso_pitch`` and ``torso_roll``, as the twin's model joints are, which
is NOT what the real torso needs: do not drive a real RX-1 torso with this driver before that
linkage is added.

Commands: one sync write per :meth:`FeetechBus.send_positions` of Acceleration (41), Goal
Position (42), Goal Time (44, always 0) and Goal Speed (46), seven bytes per servo, as the
SCServo library's ``SyncWritePosEx`` lays them out (the RX-1 driver's command). Speed and
acceleration are set in joint units (:attr:`FeetechConfig.speed_rad_s`, ``acceleration_rad_s2``)
and scaled by each servo's gear, as the RX-1 driver does. Targets are clipped to the model
limits, then to the counts the servo allows (above). Positions come back, signed, in one sync
read of Present Position (56).

Notes on ``feetech-servo-sdk`` 1.0.0 (module ``scservo_sdk``), from its source: it is only the
packet layer: no control-table constants and no sign handling (``SCS_TOHOST`` / ``SCS_TOSCS``
exist but no read or write uses them); the STS encodes negative positions and speeds as sign and
magnitude (bit 15), which ``to_sign_magnitude`` / ``from_sign_magnitude`` do (the config module).
``PacketHandler(0)`` picks little-endian words by setting a process-wide global (an SCS servo's
``PacketHandler(1)`` elsewhere in the process would flip every handler): this driver encodes and
decodes register bytes itself and only ping's model number goes through the SDK's word helper.
``GroupSyncRead.rxPacket`` drops each status packet's error byte, so reads go out through the
group and come back through ``readRx``, which keeps it; one reply timeout (``(6 + size) * n``
bytes' time + 34 ms, measured with ``time.time()``) covers all the replies of a sync read;
``clearPort`` flushes output, never input, so a late reply to an earlier request would be taken
as the answer to the next: input is discarded before every sync read here. ``rxPacket`` rejects
a status packet whose error byte is above 0x7F (it reads as noise, then a timeout).

Tested only against :mod:`beavr_sim.hardware.feetech.emulator` through the real SDK; nothing here
has touched a real RX-1 or a real STS3215.
"""

from __future__ import annotations

import numpy as np
import scservo_sdk
from scservo_sdk import PacketHandler, PortHandler

from beavr_sim.hardware.feetech.config import (
    ADDR_ACCELERATION,
    ADDR_MIN_ANGLE_LIMIT,
    ADDR_OPERATING_MODE,
    ADDR_PHASE,
    ADDR_PRESENT_POSITION,
    ADDR_TORQUE_ENABLE,
    COMMAND_SIZE,
    EAR_SERVO_IDS,
    PHASE_FULL_ANGLE_FEEDBACK,
    POSITION_MODE,
    FeetechConfig,
    allowed_counts,
    angle_to_counts,
    counts_to_angle,
    from_sign_magnitude,
    to_sign_magnitude,
)
from beavr_sim.hardware.serial_bus import BusText, ReplyTimeoutPort, SerialBus


class _Port(ReplyTimeoutPort, PortHandler):
    """The SDK's PortHandler with the reply timeout taken from the config."""


class FeetechBus(SerialBus):
    """One group of RX-1 STS3215 servos on one serial adapter. See the module docstring."""

    #: The RX-1 driver's loop rate; the servos take a new goal at any time.
    stream_hz = 100.0
    sdk = scservo_sdk
    port_class = _Port
    text = BusText(
        unit="servo",
        adapter="the servo adapter board",
        power="the servos' power supply",
        cable="the serial cable",
        ping_note=" (the RX-1 runs at 1 Mbaud)",
    )
    torque_address = ADDR_TORQUE_ENABLE
    position_block = (ADDR_PRESENT_POSITION, 2)
    goal_block = (ADDR_ACCELERATION, COMMAND_SIZE)

    def __init__(self, config: FeetechConfig) -> None:
        super().__init__(config, config.servo_ids)
        self.name = config.device_name
        self.joint_names = config.device_joint_names
        self.max_velocity = config.max_velocity
        self.model_numbers: dict[int, int] = {}  # as the servos reported them on connect
        #: (Min, Max) Angle Limit per servo id, as read on connect; (0, 0): multi-turn.
        self.angle_limits: dict[int, tuple[int, int]] = {}
        self._dirs = config.directions
        self._gears = config.gears
        self._model_lo, self._model_hi = config.count_limits()
        self._set_count_range(self._model_lo, self._model_hi)  # narrowed on connect
        self._speeds = config.speed_registers()
        self._accs = config.acceleration_registers()

    def _packet_handler(self) -> PacketHandler:
        # Sets the SDK's process-wide word order to little-endian (STS) on every connect.
        return PacketHandler(0)

    def _on_ping(self, servo_id: int, model_number: int) -> None:
        self.model_numbers[servo_id] = model_number

    def _after_ping(self) -> None:
        cfg = self.config
        wrong = {i: m for i, m in self.model_numbers.items() if m != cfg.model_number}
        if cfg.model_number is not None and wrong:
            raise self._fail(
                f"servo id(s) {sorted(wrong)} on {cfg.port!r} report model number(s) "
                f"{[wrong[i] for i in sorted(wrong)]}, expected {cfg.model_number} (STS3215); "
                f"check the servo ids (an SCS ear servo, ids {list(EAR_SERVO_IDS)}, must never "
                f"be driven as an STS)"
            )

    def _set_up(self) -> None:
        self._check_modes()
        self._check_angle_limits()
        # Goal = present before torque on: a stale goal cannot make the robot jump.
        self._write_goal_counts(self._read_counts(), count=False)
        for i in self._ids:
            self._write_register(i, ADDR_TORQUE_ENABLE, 1, 1, "torque enable")

    def hold(self) -> None:
        """Re-send the last target (or, if none was sent, the measured pose) and stay there;
        the next :meth:`send_positions` resumes following.

        An STS servo in position mode keeps going to its last goal on its own, so holding needs
        no new goal; re-sending the last one covers a lost sync write (it has no reply). Writing
        the present position instead would be wrong on the geared joints: under gravity they
        sit some counts below their goal, and every hold would lower the arm by that much.
        """
        super().hold()

    def _to_model(self, counts: np.ndarray) -> np.ndarray:
        return counts_to_angle(counts, self._dirs, self._gears)

    def _to_counts(self, q: np.ndarray) -> np.ndarray:
        # Clip in radians first (no int overflow for huge targets), then to whole counts.
        q = np.clip(q, self._q_lo, self._q_hi)
        counts = angle_to_counts(q, self._dirs, self._gears)
        return np.clip(counts, self._lo_counts, self._hi_counts)

    def _goal_counts_of(self, q: np.ndarray) -> np.ndarray:
        return angle_to_counts(q, self._dirs, self._gears)

    def _decode_position(self, data: bytes) -> int:
        return from_sign_magnitude(int.from_bytes(data, "little"))

    def _goal_bytes(self, k: int, counts: int) -> bytes:
        return (
            bytes([int(self._accs[k])])
            + to_sign_magnitude(counts).to_bytes(2, "little")
            + bytes(2)  # Goal Time: 0, the speed register rules
            + to_sign_magnitude(int(self._speeds[k])).to_bytes(2, "little")
        )

    def _status_error_text(self, servo_id: int, error: int) -> str:
        return (
            f"servo {servo_id} reports {self._error_text(error)} (status 0x{error:02x}); check "
            f"its load, temperature and supply voltage, then enable torque again (a protection "
            f"may have cut it)"
        )

    def _set_count_range(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """The goal counts sent from now on, and the joint angles they span (for clipping in
        radians before rounding)."""
        self._lo_counts, self._hi_counts = lo, hi
        ends = counts_to_angle(np.stack([lo, hi]), self._dirs, self._gears)
        self._q_lo, self._q_hi = ends.min(axis=0), ends.max(axis=0)

    def _check_modes(self) -> None:
        for i in self._ids:
            mode = self._read_register(i, ADDR_OPERATING_MODE, 1, "the operating mode")[0]
            if mode != POSITION_MODE:
                raise self._fail(
                    f"servo {i} is in operating mode {mode}, not position mode "
                    f"({POSITION_MODE}); set Operating_Mode (33) to 0 with Feetech's tools"
                )

    def _check_angle_limits(self) -> None:
        """Read every servo's angle limits; refuse a servo whose model joint range does not fit
        in the counts they allow, or a multi-turn one that reports its position within one turn
        only; then narrow the goal range to what each servo allows."""
        limits: dict[int, tuple[int, int]] = {}
        for i in self._ids:
            raw = self._read_register(i, ADDR_MIN_ANGLE_LIMIT, 4, "the angle limits (9, 11)")
            limits[i] = (int.from_bytes(raw[:2], "little"), int.from_bytes(raw[2:], "little"))
        allowed: list[tuple[int, int]] = []
        for i in self._ids:
            try:
                allowed.append(allowed_counts(*limits[i]))
            except ValueError as exc:
                raise self._fail(
                    f"servo {i}: {exc}; set them with Feetech's FD tool: both 0 for "
                    f"multi-turn, as the RX-1 runs every servo behind a 3:1 gearbox"
                ) from None
        a_lo, a_hi = (np.array(column, dtype=np.int64) for column in zip(*allowed, strict=True))
        lo, hi = self._model_lo, self._model_hi
        lo_known, hi_known = self.config.limited_count_sides()
        misfit = (lo_known & (lo < a_lo)) | (hi_known & (hi > a_hi)) | (hi < a_lo) | (lo > a_hi)
        if misfit.any():
            bad = [k for k in range(len(self._ids)) if misfit[k]]
            needed = [
                (f"{lo[k]}" if lo_known[k] else "-inf", f"{hi[k]}" if hi_known[k] else "inf")
                for k in range(len(self._ids))
            ]
            details = "; ".join(
                f"{self._ids[k]} {self.joint_names[k]}: needs counts {needed[k][0]}.."
                f"{needed[k][1]}, angle limits {limits[self._ids[k]]} allow {a_lo[k]}..{a_hi[k]}"
                for k in bad
            )
            raise self._fail(
                f"servo(s) {[self._ids[k] for k in bad]} cannot reach their model joint range "
                f"({details}); a servo whose angle limits (Min 9, Max 11) are set stays within "
                f"one turn, counts 0..4095: set both to 0 with Feetech's FD tool, multi-turn "
                f"position operation, as the RX-1 runs every servo behind a 3:1 gearbox "
                f"(Red-Rabbit-Robotics/rx1 issue #3), and set bit 4 of its Phase (18) so it "
                f"reports the full angle (or, for a range within one turn, widen the limits)"
            )
        multi = [i for i in self._ids if limits[i] == (0, 0)]
        one_turn_feedback = [
            i
            for i in multi
            if not self._read_register(i, ADDR_PHASE, 1, "the phase (18)")[0]
            & PHASE_FULL_ANGLE_FEEDBACK
        ]
        if one_turn_feedback:
            raise self._fail(
                f"servo(s) {one_turn_feedback} run multi-turn (angle limits 0 and 0) but report "
                f"their position within one turn (Phase (18) bit 4 clear): the driver could not "
                f"tell where their joints are; set bit 4 of Phase (add 16) with Feetech's FD tool"
            )
        self.angle_limits = limits
        self._set_count_range(np.maximum(lo, a_lo), np.minimum(hi, a_hi))
