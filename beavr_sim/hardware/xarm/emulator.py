"""An emulated xArm7 controller: the part of UFACTORY's private Modbus-TCP protocol the driver uses.

What is emulated (written from the framing and register ids in ``xarm-python-sdk`` 1.18.4:
``xarm/core/wrapper/uxbus_cmd*.py``, ``xarm/core/config/x_config.py``); nothing here ran
against a real xArm, and the controller's behaviour below is a model, not a measurement:

* Transport: one TCP listener on 127.0.0.1 (an ephemeral port unless given), served by a daemon
  thread; every connection gets its own thread, carries any number of requests, and clients may
  reconnect. No real-time report stream is served: drive it with ``enable_report=False``.
* Framing: request = transaction id (u16 BE), protocol id (u16 BE; 2, or 3 once a reporting
  SDK switches), length (u16 BE) = 1 + parameter bytes, register (u8), parameters. Reply =
  the same transaction and protocol ids, length = 2 + data bytes, register, a state byte
  (0x40 error present, 0x20 warning present, 0x10 not ready to move, 0x08 invalid request),
  data. Floats are little-endian fp32.
* Registers: 1 version, 2 serial numbers, 11 motion enable, 12/13 set/get state, 14 command
  count, 15 error + warning code, 16/17 clean error/warning, 19 set mode, 29 servo_j, 34 joint
  max acceleration, 37 collision sensitivity, 42 joint positions (with a ``num`` byte: joint
  states), 48 reduced max joint speed, 49/50 get/set reduced mode, 52 reduced TCP boundary,
  58 reduced joint ranges, 77 self-collision detection, 253/254 feedback check/type (accepted;
  no feedback frames are sent). Anything else is answered with the invalid flag and counted in
  :attr:`XArmEmulator.unknown_registers`. Safety settings are stored for tests to read; of
  them only the reduced max joint speed and the joint max acceleration shape the motion.

Controller model:

* States as ``get_state`` reports them: 1 moving, 2 ready (idle), 3 paused, 4 stopped. Power-on
  is stopped, mode 0, motors disabled. ``set_state(0)`` starts (and applies the mode last given
  to ``set_mode``) only when the motors are enabled and no error is set; "state 0" is this
  command, the running arm then reports 1 or 2.
* Servo model, advanced by wall time: in mode 1 while started, each joint moves toward the
  latest accepted servo_j target with velocity at most the speed cap (``speed_limit``, default
  pi rad/s, lowered to the reduced max joint speed while reduced mode is on) and acceleration at
  most the joint max acceleration. Speed, acceleration and time fields of servo_j are ignored.
* Faults: a servo_j target outside the xArm7 joint limits raises error 23; a target farther
  from the previous accepted target than ``speed cap * servo_period_s`` raises error 24 (the
  speed it implies at the nominal streaming period). :meth:`XArmEmulator.inject_error` sets any
  code. An error stops the arm (state 4), disables the motors and makes every reply carry the
  error flag; servo_j is ignored until ``clean_error``, ``motion_enable(True)`` and
  ``set_state(0)``. Warnings (:meth:`XArmEmulator.inject_warning`) only flag replies.

Test hooks: :attr:`servo_log` (every servo_j received: time and 7 floats, accepted or not),
:attr:`accepted_servo`, :attr:`joints`, :attr:`state`, :attr:`mode`, the safety settings,
:meth:`kill` (drop every connection and stop answering), :meth:`inject` (faults: freeze, drop,
corrupt, delay, disconnect; :mod:`beavr_sim.hardware.faults`), :attr:`host`, :attr:`port`.
"""

from __future__ import annotations

import math
import socket
import struct
import threading
import time
from collections.abc import Callable

import numpy as np

from beavr_sim.hardware.faults import Fate, FaultSpec, FaultState, Verdict
from beavr_sim.hardware.servo_model import step_towards
from beavr_sim.hardware.xarm.config import XARM7_JOINT_LIMITS

_LOWER = np.array([lo for lo, _ in XARM7_JOINT_LIMITS])
_UPPER = np.array([hi for _, hi in XARM7_JOINT_LIMITS])
_LIMIT_TOL = 1e-6  # rad: fp32 rounding of a target exactly on a limit stays inside

# Reply state-byte flags (uxbus_cmd_tcp.check_private_protocol).
FLAG_INVALID = 0x08
FLAG_NOT_READY = 0x10
FLAG_WARNING = 0x20
FLAG_ERROR = 0x40

STATE_MOVING, STATE_READY, STATE_PAUSED, STATE_STOPPED = 1, 2, 3, 4
ERROR_JOINT_LIMIT, ERROR_SPEED = 23, 24

_HEADER = struct.Struct(">HHH")
_SUBSTEP_S = 0.001
_BOX_SERIAL = "AC1300EMU01"


class XArmEmulator:
    """A controller speaking the xArm private Modbus-TCP protocol on ``host:port``.

    ``port=0`` (the default) binds an ephemeral port; read it back from :attr:`port`.
    Use as a context manager or call :meth:`close` (same as :meth:`kill`).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        initial_joints: tuple[float, ...] | None = None,
        speed_limit: float = math.pi,
        max_acc: float = 20.0,
        servo_period_s: float = 0.01,
        firmware: str = "2.5.5",
        serial: str = "XI1303EMU00001",
        name: str = "xarm",
    ) -> None:
        q0 = np.zeros(7) if initial_joints is None else np.array(initial_joints, dtype=float)
        if q0.shape != (7,):
            raise ValueError(f"initial_joints must have 7 values, got {initial_joints!r}")
        self.speed_limit = float(speed_limit)
        self.servo_period_s = float(servo_period_s)
        self.firmware = firmware
        self.serial = serial

        self._lock = threading.Lock()
        self._q = q0.copy()
        self._v = np.zeros(7)
        self._target = q0.copy()
        self._t = time.monotonic()
        self._enabled = False
        self._started = False  # set_state(0) went through; 3/4 stop it
        self._paused = False
        self._mode = 0
        self._pending_mode = 0
        self._error = 0
        self._warn = 0

        #: Every servo_j received: (monotonic time, 7 joint targets), accepted or not.
        self.servo_log: list[tuple[float, tuple[float, ...]]] = []
        #: How many servo_j targets the controller accepted (moved toward).
        self.accepted_servo = 0
        #: Every ``set_state`` value received, in order.
        self.set_state_log: list[int] = []
        #: Register ids of every request, in order.
        self.request_log: list[int] = []
        #: Registers answered with the invalid flag because they are not emulated.
        self.unknown_registers: list[int] = []
        self.collision_sensitivity: int | None = None
        self.self_collision_detection: bool | None = None
        self.reduced_mode = False
        self.reduced_max_joint_speed: float | None = None
        self.reduced_joint_ranges: tuple[tuple[float, float], ...] | None = None
        self.tcp_boundary_mm: tuple[int, ...] | None = None
        self.joint_max_acc = float(max_acc)

        self._handlers: dict[int, Callable[[bytes], tuple[int, bytes]]] = {
            1: self._get_version,
            2: self._get_sn,
            11: self._motion_enable,
            12: self._set_state,
            13: lambda p: (0, bytes([self._reported_state()])),
            14: lambda p: (0, struct.pack(">H", 0)),
            15: lambda p: (0, bytes([self._error, self._warn])),
            16: self._clean_error,
            17: self._clean_warn,
            19: self._set_mode,
            29: self._servo_j,
            34: self._set_joint_maxacc,
            37: self._set_collision_sensitivity,
            42: self._get_joints,
            48: self._set_reduced_joint_speed,
            49: lambda p: (0, bytes([int(self.reduced_mode)])),
            50: self._set_reduced_mode,
            52: self._set_tcp_boundary,
            58: self._set_reduced_joint_ranges,
            77: self._set_self_collision,
            253: lambda p: (0, b""),
            254: lambda p: (0, b""),
        }

        #: The injected faults (:meth:`inject`) and their counters.
        self.fault_state = FaultState(name)
        self._killed = threading.Event()
        self._conns: list[socket.socket] = []
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((host, port))
        self._listener.listen(8)
        self._listener.settimeout(0.1)
        self.host, self.port = self._listener.getsockname()[:2]
        threading.Thread(target=self._accept_loop, name="xarm-emulator", daemon=True).start()

    # ----------------------------------------------------------------- test hooks

    @property
    def joints(self) -> np.ndarray:
        """Current joint positions (rad), advanced to now."""
        with self._lock:
            self._advance()
            return self._q.copy()

    @property
    def state(self) -> int:
        """The state ``get_state`` would report now (1 moving, 2 ready, 3 paused, 4 stopped)."""
        with self._lock:
            self._advance()
            return self._reported_state()

    @property
    def mode(self) -> int:
        """The active mode (0 position, 1 servo, ...)."""
        return self._mode

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def error_code(self) -> int:
        return self._error

    @property
    def warn_code(self) -> int:
        return self._warn

    @property
    def speed_cap(self) -> float:
        """Joint speed cap (rad/s): ``speed_limit``, or the reduced one in reduced mode."""
        if self.reduced_mode and self.reduced_max_joint_speed:
            return min(self.speed_limit, self.reduced_max_joint_speed)
        return self.speed_limit

    def inject_error(self, code: int) -> None:
        """Raise controller error ``code`` (stops the arm, as a real fault would)."""
        with self._lock:
            self._advance()
            self._fault(code)

    def inject_warning(self, code: int) -> None:
        """Raise controller warning ``code`` (flags replies; motion continues)."""
        with self._lock:
            self._warn = int(code)

    def inject(self, spec: FaultSpec) -> None:
        """Put the controller under ``spec`` (:mod:`beavr_sim.hardware.faults`): a request
        that arrives frozen is lost unanswered (and does nothing); a reply may be dropped,
        garbled (its protocol id: the SDK rejects it) or late; ``disconnect`` is :meth:`kill`,
        at ``@T`` or at the next request."""
        self.fault_state.add(spec)
        if spec.kind == "disconnect" and spec.at_s is not None:
            timer = threading.Timer(spec.at_s, self.kill)
            timer.daemon = True
            timer.start()

    def kill(self) -> None:
        """Drop every connection and stop answering (the listener closes too)."""
        self._killed.set()
        for s in [self._listener, *self._conns]:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    close = kill

    def __enter__(self) -> XArmEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill()

    # ------------------------------------------------------------------ transport

    def _accept_loop(self) -> None:
        while not self._killed.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.1)
            self._conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        buf = b""
        while not self._killed.is_set():
            try:
                chunk = conn.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                break
            if not chunk:
                break
            buf += chunk
            while len(buf) >= 6:
                size = 6 + _HEADER.unpack_from(buf)[2]
                if len(buf) < size:
                    break
                frame, buf = buf[:size], buf[size:]
                verdict = self.fault_state.admit()
                if verdict is Verdict.DISCONNECTED:
                    self.kill()
                    break
                reply = self._reply(frame) if verdict is Verdict.SERVE else None
                fate = self.fault_state.fate() if reply else Fate.DROP
                if fate is Fate.CORRUPT:
                    reply = reply[:2] + b"\xff\xff" + reply[4:]  # a protocol id the SDK refuses
                if fate is not Fate.DROP and self.fault_state.delay_s > 0:
                    time.sleep(self.fault_state.delay_s)
                if fate is not Fate.DROP and not self._killed.is_set():
                    try:
                        conn.sendall(reply)
                    except OSError:
                        break
        try:
            conn.close()
        except OSError:
            pass
        if conn in self._conns:
            self._conns.remove(conn)

    def _reply(self, frame: bytes) -> bytes | None:
        trans_id, prot_id, length = _HEADER.unpack_from(frame)
        if prot_id not in (2, 3) or length < 1:  # heartbeat (protocol 1) or standard Modbus
            return None
        register, params = frame[6], frame[7:]
        with self._lock:
            self._advance()
            self.request_log.append(register)
            handler = self._handlers.get(register)
            if handler is None:
                self.unknown_registers.append(register)
                flags, data = FLAG_INVALID, b""
            else:
                try:
                    flags, data = handler(params)
                except (struct.error, IndexError, ValueError):
                    flags, data = FLAG_INVALID, b""
            flags |= self._status_flags()
        return _HEADER.pack(trans_id, prot_id, 2 + len(data)) + bytes([register, flags]) + data

    # ---------------------------------------------------------------- controller

    def _status_flags(self) -> int:
        flags = FLAG_ERROR if self._error else 0
        flags |= FLAG_WARNING if self._warn else 0
        if not (self._enabled and self._started):
            flags |= FLAG_NOT_READY
        return flags

    def _reported_state(self) -> int:
        if not self._started:
            return STATE_STOPPED
        if self._paused:
            return STATE_PAUSED
        moving = np.any(self._v != 0.0) or np.any(self._q != self._target)
        return STATE_MOVING if moving else STATE_READY

    def _stop(self) -> None:
        self._started = False
        self._paused = False
        self._v[:] = 0.0
        self._target = self._q.copy()

    def _fault(self, code: int) -> None:
        self._error = int(code)
        self._enabled = False
        self._stop()

    def _advance(self) -> None:
        """Integrate the servo model (:func:`~beavr_sim.hardware.servo_model.step_towards`)
        from the last call to now, in 1 ms substeps."""
        now = time.monotonic()
        elapsed, self._t = now - self._t, now
        if not (self._started and not self._paused and self._mode == 1):
            return
        vmax, amax = self.speed_cap, self.joint_max_acc
        while elapsed > 0.0:
            if np.all(self._q == self._target) and np.all(self._v == 0.0):
                return
            dt = min(_SUBSTEP_S, elapsed)
            elapsed -= dt
            self._q, self._v = step_towards(self._q, self._target, dt, vmax, self._v, amax)

    # ----------------------------------------------------------------- registers

    @staticmethod
    def _u8(params: bytes) -> int:
        if len(params) < 1:
            raise ValueError("missing u8 parameter")
        return params[0]

    @staticmethod
    def _fp32(params: bytes, n: int) -> tuple[float, ...]:
        return struct.unpack_from(f"<{n}f", params)

    def _get_version(self, params: bytes) -> tuple[int, bytes]:
        # NUL-terminated: the SDK cuts the text at the first NUL.
        text = f"7,7,{self.serial},{_BOX_SERIAL},v{self.firmware}".encode()
        return 0, text[:39].ljust(40, b"\0")

    def _get_sn(self, params: bytes) -> tuple[int, bytes]:
        return 0, f"{self.serial}\0{_BOX_SERIAL}\0".encode()[:40].ljust(40, b"\0")

    def _motion_enable(self, params: bytes) -> tuple[int, bytes]:
        axis, on = params[0], params[1]
        if axis != 8:  # single joints: accepted, but the model enables the arm as a whole
            return 0, b""
        if not on:
            self._enabled = False
            self._stop()
        elif not self._error:
            self._enabled = True
        return 0, b""

    def _set_state(self, params: bytes) -> tuple[int, bytes]:
        value = self._u8(params)
        self.set_state_log.append(value)
        if value == 0:
            if self._error or not self._enabled:
                return 0, b""
            if not self._started or self._mode != self._pending_mode:
                self._mode = self._pending_mode
                self._stop()
                self._started = True
            self._paused = False
        elif value == 3 and self._started:
            self._paused = True
            self._v[:] = 0.0
        elif value == 4:
            self._stop()
        elif value not in (3, 4):
            return FLAG_INVALID, b""
        return 0, b""

    def _clean_error(self, params: bytes) -> tuple[int, bytes]:
        self._error = 0
        return 0, b""

    def _clean_warn(self, params: bytes) -> tuple[int, bytes]:
        self._warn = 0
        return 0, b""

    def _set_mode(self, params: bytes) -> tuple[int, bytes]:
        self._pending_mode = self._u8(params)
        return 0, b""

    def _servo_j(self, params: bytes) -> tuple[int, bytes]:
        values = self._fp32(params, 10)
        target = np.array(values[:7])
        self.servo_log.append((time.monotonic(), tuple(values[:7])))
        if self._error or not (self._enabled and self._started) or self._paused:
            return 0, b""
        if self._mode != 1:
            return 0, b""
        if not np.all(np.isfinite(target)) or np.any(target < _LOWER - _LIMIT_TOL):
            self._fault(ERROR_JOINT_LIMIT)
        elif np.any(target > _UPPER + _LIMIT_TOL):
            self._fault(ERROR_JOINT_LIMIT)
        elif np.max(np.abs(target - self._target)) > self.speed_cap * self.servo_period_s + 1e-6:
            self._fault(ERROR_SPEED)
        else:
            self._target = target
            self.accepted_servo += 1
        return 0, b""

    def _get_joints(self, params: bytes) -> tuple[int, bytes]:
        if not params:
            return 0, struct.pack("<7f", *self._q)
        num = params[0] & 0x0F
        rows = [self._q, self._v, np.zeros(7)][:num]
        return 0, b"".join(struct.pack("<7f", *row) for row in rows)

    def _set_joint_maxacc(self, params: bytes) -> tuple[int, bytes]:
        (acc,) = self._fp32(params, 1)
        if not 0.0 < acc <= 20.0:
            return FLAG_INVALID, b""
        self.joint_max_acc = acc
        return 0, b""

    def _set_collision_sensitivity(self, params: bytes) -> tuple[int, bytes]:
        value = self._u8(params)
        if value > 5:
            return FLAG_INVALID, b""
        self.collision_sensitivity = value
        return 0, b""

    def _set_reduced_joint_speed(self, params: bytes) -> tuple[int, bytes]:
        (speed,) = self._fp32(params, 1)
        if not 0.0 < speed <= math.pi + 1e-6:
            return FLAG_INVALID, b""
        self.reduced_max_joint_speed = speed
        return 0, b""

    def _set_reduced_mode(self, params: bytes) -> tuple[int, bytes]:
        self.reduced_mode = bool(self._u8(params))
        return 0, b""

    def _set_tcp_boundary(self, params: bytes) -> tuple[int, bytes]:
        self.tcp_boundary_mm = struct.unpack_from("<6i", params)
        return 0, b""

    def _set_reduced_joint_ranges(self, params: bytes) -> tuple[int, bytes]:
        flat = self._fp32(params, 14)
        self.reduced_joint_ranges = tuple((flat[2 * i], flat[2 * i + 1]) for i in range(7))
        return 0, b""

    def _set_self_collision(self, params: bytes) -> tuple[int, bytes]:
        self.self_collision_detection = bool(self._u8(params))
        return 0, b""
