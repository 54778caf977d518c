"""xArm7 driver: streams joint targets through UFACTORY's own SDK (``xarm-python-sdk``).

:class:`XArm7` talks to the controller through the real ``xarm.wrapper.XArmAPI`` (radians,
``forbid_uds=True``): ``connect`` clears errors, enables the motors, applies the safety set of
:class:`XArmConfig` (collision sensitivity, self-collision detection, reduced mode with its max
joint speed, joint ranges and TCP boundary, joint max acceleration), then ``set_mode(1)``
(servo) and ``set_state(0)``. ``send_positions`` is one ``set_servo_angle_j`` (the controller
executes only the latest target), ``read_positions`` one ``get_servo_angle``.

Joint convention: the model's xArm7 joints use the controller's zero, sign and radians, so no
conversion is applied. Targets travel as little-endian fp32; :meth:`XArm7.send_positions`
returns the fp32-rounded vector, exactly what the controller receives.

Port: the SDK hard-codes the control port (``XCONF.SocketConf.TCP_CONTROL_PORT`` = 502) and has
no constructor argument for it. With ``XArmConfig.port`` set, the driver patches that constant
under a module lock only until the SDK's control socket is open (its port is read when the
socket is built), then restores it; the report ports cannot be redirected this way, so a custom
port requires ``enable_report=False``. Tested only against
:mod:`beavr_sim.hardware.xarm.emulator`; nothing here has run on a real xArm.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from beavr_sim.hardware.device import Device, DeviceError
from beavr_sim.hardware.xarm.config import XArmConfig

#: Controller error codes (``xarm/core/config/x_code.py``), by name.
CONTROLLER_ERRORS: dict[int, str] = {
    1: "emergency stop",
    2: "emergency stop",
    3: "emergency stop",
    10: "servo motor error",
    **{10 + j: f"servo motor {j} error" for j in range(1, 8)},
    18: "force-torque sensor communication error",
    19: "end effector communication error",
    21: "kinematic error",
    22: "self-collision",
    23: "joint angle over limit",
    24: "speed over limit",
    25: "planning error",
    31: "collision current",
    35: "safety boundary",
    38: "abnormal joint angle",
    60: "servo_j linear speed over limit",
}

#: Controller warning codes (``x_code.py``), by name.
CONTROLLER_WARNINGS: dict[int, str] = {
    11: "command buffer full",
    12: "command parameter error",
    13: "unknown command",
    14: "command has no solution",
    15: "modbus command buffer full",
}

#: SDK return codes (``xarm/x3/code.py``, ``XCONF.UxbusState``), for messages.
SDK_CODES: dict[int, str] = {
    -1: "not connected",
    -2: "not ready",
    -3: "API exception",
    -8: "out of range",
    1: "controller has an error",
    2: "controller has a warning",
    3: "no reply in time",
    4: "reply length error",
    5: "reply sequence error",
    8: "send failed",
    9: "state not ready to move",
    10: "request invalid or failed",
    12: "parameter error",
}

_HAS_ERROR, _HAS_WARNING = 1, 2
#: SDK codes of a reply that did not come in time or came garbled: asked again (``retries``).
_TRANSIENT = frozenset({3, 4, 5, 6, 7})
_WHAT_TO_CHECK = (
    "check that the controller is powered on, the network link to it, the controller's IP "
    "address and port, and that the emergency stop is released"
)


def controller_code_name(code: int) -> str:
    """The name of controller error ``code`` (``"controller error <n>"`` when unknown)."""
    return CONTROLLER_ERRORS.get(code, f"controller error {code}")


def controller_warning_name(code: int) -> str:
    """The name of controller warning ``code`` (``"controller warning <n>"`` when unknown)."""
    return CONTROLLER_WARNINGS.get(code, f"controller warning {code}")


def _sdk_code(code: int) -> str:
    return f"SDK code {code} ({SDK_CODES.get(code, 'unknown')})"


class ServoCommandError(DeviceError):
    """A ``send_positions`` failure; ``sent`` is the fp32 target that reached the SDK (or None)."""

    def __init__(self, message: str, sent: np.ndarray | None) -> None:
        super().__init__(message)
        self.sent = sent


_SDK_PORT_LOCK = threading.Lock()


class XArm7(Device):
    """One xArm7 arm streaming joint targets in servo mode (mode 1) through ``XArmAPI``."""

    #: servo_j executes only the latest target and expects a stream: UFACTORY's examples
    #: send at 100 Hz, and a larger step per target trips the speed check (error 24).
    stream_hz = 100.0

    def __init__(
        self,
        config: XArmConfig,
        name: str = "right",
        joint_names: tuple[str, ...] | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        #: Monotonic seconds for the connect deadline (tests inject one).
        self._clock = clock
        self.name = name
        self.joint_names = joint_names or tuple(f"{name}/joint{i}" for i in range(1, 8))
        if len(self.joint_names) != 7:
            raise ValueError(f"{name}: an xArm7 drives 7 joints, got {len(self.joint_names)} names")
        #: The controller refuses faster targets (error 24): a mirror stays under this.
        self.max_velocity = config.max_joint_speed if config.reduced_mode else math.pi
        self._api: Any = None
        self._last_sent: np.ndarray | None = None
        self._fault: tuple[int, str] | None = None
        #: Targets the controller acknowledged (``send_positions`` and ``hold``).
        self.commands_sent = 0
        #: DeviceErrors raised by this driver.
        self.errors = 0
        #: Requests asked again after no reply in time or a garbled one (SDK codes 3-7).
        self.retries = 0

    # ------------------------------------------------------------------ lifecycle

    @property
    def where(self) -> str:
        port = 502 if self.config.port is None else self.config.port
        return f"{self.name} (xArm7 at {self.config.host}:{port})"

    @property
    def api(self) -> Any:
        """The underlying ``XArmAPI`` (None when disconnected), for calls this class lacks."""
        return self._api

    def connect(self) -> None:
        if self._api is not None:
            return
        self._connect(self.config.connect_timeout_s)

    def reconnect(self) -> np.ndarray:
        """A new TCP connection, the set-up of :meth:`connect` (servo mode again: the arm
        holds where it is until the next target), and the measured joints. The connection must
        come up within ``command_timeout_s`` (not ``connect_timeout_s``), so a controller that
        does not answer fails fast; safe to call again."""
        self.disconnect()
        self._connect(self.config.command_timeout_s)
        return self.read_positions()

    def _connect(self, timeout_s: float) -> None:
        self._api = self._open(timeout_s)
        try:
            self._api.set_timeout(self.config.command_timeout_s)
            if self._api.axis != 7:
                raise self._error(f"controller reports a {self._api.axis}-axis arm, not an xArm7")
            self._check("clean_error", self._api.clean_error())
            self._check("motion_enable", self._api.motion_enable(True))
            # Stopped while the safety set changes; the SDK's wait for running motion inside
            # set_collision_sensitivity then returns at once.
            self._check("set_state", self._api.set_state(4))
            self._apply_safety()
            self._start_servo()
        except Exception as e:
            self.disconnect()
            if isinstance(e, DeviceError):
                raise
            raise self._error(f"set-up raised {type(e).__name__}: {e}") from e

    def _open(self, timeout_s: float) -> Any:
        """``XArmAPI`` connected within ``timeout_s``, or DeviceError."""
        _sdk_output_to_stderr()
        from xarm.core.config.x_config import XCONF
        from xarm.wrapper import XArmAPI

        _quiet_mode_reminder()
        cfg = self.config
        api = XArmAPI(
            cfg.host,
            is_radian=True,
            do_not_open=True,
            enable_report=cfg.enable_report,
            forbid_uds=True,
        )
        outcome: dict[str, BaseException | None] = {}
        done = threading.Event()

        def work() -> None:
            try:
                api.connect()
                outcome["error"] = None
            except Exception as e:  # the SDK raises bare Exception
                outcome["error"] = e
            done.set()

        clock = self._clock
        deadline = clock() + timeout_s
        worker = threading.Thread(target=work, name=f"{self.name}-connect", daemon=True)
        with _SDK_PORT_LOCK:
            saved = XCONF.SocketConf.TCP_CONTROL_PORT
            if cfg.port is not None:
                XCONF.SocketConf.TCP_CONTROL_PORT = cfg.port
            try:
                worker.start()
                # The SDK reads the port while building its control socket: hold the patch
                # until that socket is connected, the attempt failed, or time is up.
                while not (api.connected or done.is_set() or clock() > deadline):
                    time.sleep(0.001)
            finally:
                XCONF.SocketConf.TCP_CONTROL_PORT = saved
        while not done.is_set() and clock() <= deadline:
            done.wait(0.01)
        if not done.is_set():
            _quiet_disconnect(api)  # the SDK's version check then gives up on its own
            raise self._error(f"no answer within {timeout_s:g} s; {_WHAT_TO_CHECK}")
        if outcome["error"] is not None or not api.connected:
            _quiet_disconnect(api)
            raise self._error(f"cannot connect ({outcome['error']}); {_WHAT_TO_CHECK}")
        return api

    def _apply_safety(self) -> None:
        cfg, api = self.config, self._api
        self._check(
            "set_collision_sensitivity", api.set_collision_sensitivity(cfg.collision_sensitivity)
        )
        self._check(
            "set_self_collision_detection",
            api.set_self_collision_detection(cfg.self_collision_detection),
        )
        if cfg.reduced_mode:
            self._check(
                "set_reduced_max_joint_speed",
                api.set_reduced_max_joint_speed(cfg.max_joint_speed, is_radian=True),
            )
            if cfg.reduced_joint_ranges is not None:
                flat = [x for pair in cfg.reduced_joint_ranges for x in pair]
                self._check(
                    "set_reduced_joint_range", api.set_reduced_joint_range(flat, is_radian=True)
                )
            if cfg.tcp_boundary_mm is not None:
                self._check(
                    "set_reduced_tcp_boundary",
                    api.set_reduced_tcp_boundary(list(cfg.tcp_boundary_mm)),
                )
        self._check("set_reduced_mode", api.set_reduced_mode(cfg.reduced_mode))
        self._check("set_joint_maxacc", api.set_joint_maxacc(cfg.max_joint_acc, is_radian=True))

    def _start_servo(self) -> None:
        """Servo mode, started; DeviceError if the controller has an error or stays stopped."""
        self._check("set_mode", self._api.set_mode(1))
        self._check("set_state", self._api.set_state(0))
        codes = self._read_codes()
        if codes is not None and codes[0]:
            raise self._error(
                f"controller error {controller_code_name(codes[0])} (code {codes[0]}) after start"
            )
        code, state = self._api.get_state()
        if code != 0 or state >= 4:
            raise self._error(
                f"controller did not start (get_state: {_sdk_code(code)}, state {state}); {_WHAT_TO_CHECK}"
            )
        self._fault = None

    def recover(self) -> None:
        """After a controller error: ``clean_error``, ``motion_enable``, servo mode, start."""
        api = self._require()
        self._check("clean_error", api.clean_error())
        self._check("motion_enable", api.motion_enable(True))
        self._start_servo()

    def disconnect(self) -> None:
        api, self._api = self._api, None
        self._last_sent = None
        if api is not None:
            _quiet_disconnect(api)

    # ------------------------------------------------------------------ streaming

    def read_positions(self) -> np.ndarray:
        api = self._require()
        code, angles = self._request("get_servo_angle", api.get_servo_angle, is_radian=True)
        if code != 0:
            raise self._error(f"get_servo_angle failed: {_sdk_code(code)}")
        return np.asarray(angles[:7], dtype=np.float64)

    def send_positions(self, positions: np.ndarray) -> np.ndarray:
        q = self.check_positions(positions)
        with np.errstate(over="ignore"):
            q32 = q.astype(np.float32)
        if not np.isfinite(q32).all():
            raise ValueError(f"{self.name}: joint targets beyond fp32 range {q.tolist()}")
        self._require()
        if self._fault is not None:
            code, name = self._fault
            raise self._servo_error(
                f"holding after controller error {name} (code {code}); call recover()", None
            )
        sent = q32.astype(np.float64)
        self._servo(sent)
        self._last_sent = sent
        return sent.copy()

    def hold(self) -> None:
        """Stop streaming: re-send the last target once (the controller keeps the latest).

        With no target sent since connect or the last controller error (which stops the arm
        where it is), nothing is sent: the controller already holds its pose.
        """
        self._require()
        if self._last_sent is not None:
            self._servo(self._last_sent)

    def _servo(self, q: np.ndarray) -> None:
        code = self._request(
            "set_servo_angle_j", self._api.set_servo_angle_j, q.tolist(), is_radian=True
        )
        if code == 0:
            self.commands_sent += 1
            return
        codes = self._read_codes() if code == _HAS_ERROR else None
        if codes is not None and codes[0]:
            fault = self._note_error(codes[0])
            raise self._servo_error(
                f"set_servo_angle_j refused: controller error {fault[1]} (code {fault[0]}); "
                "the arm holds until recover()",
                q,
            )
        # Negative codes and 8 (send failed) are refusals before anything reached the wire.
        on_wire = code >= 0 and code != 8
        raise self._servo_error(
            f"set_servo_angle_j failed: {_sdk_code(code)}", q if on_wire else None
        )

    # -------------------------------------------------------------------- status

    @property
    def fault(self) -> tuple[int, str] | None:
        """(code, name) of the controller's error, else of its warning, else None.

        Read from the controller when it answers; the last error seen otherwise.
        """
        codes = None if self._api is None else self._read_codes()
        if codes is None:
            return self._fault
        error, warn = codes
        if error:
            return self._note_error(error)
        return (warn, controller_warning_name(warn)) if warn else None

    def _read_codes(self) -> tuple[int, int] | None:
        """(error code, warning code) from the controller, or None when it does not answer."""
        try:
            code, (error, warn) = self._api.get_err_warn_code()
        except Exception:
            return None
        return (int(error), int(warn)) if code == 0 else None

    def _note_error(self, code: int) -> tuple[int, str]:
        # The controller stopped the arm where it was: the last target is stale.
        self._last_sent = None
        self._fault = (code, controller_code_name(code))
        return self._fault

    # ------------------------------------------------------------------- helpers

    def _require(self) -> Any:
        if self._api is None:
            raise self._error("not connected; call connect() first")
        return self._api

    def _call(self, call: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except Exception as e:
            raise self._error(f"{call} raised {type(e).__name__}: {e}") from e

    def _request(self, call: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """:meth:`_call`, asked again up to ``retries`` times while the SDK reports no reply in
        time or a garbled one (both requests are idempotent: the latest target, a read)."""
        for attempt in range(self.config.retries + 1):
            result = self._call(call, fn, *args, **kwargs)
            code = result[0] if isinstance(result, tuple) else result
            if code not in _TRANSIENT or attempt == self.config.retries:
                return result
            self.retries += 1
        return result

    def _check(self, call: str, code: int) -> None:
        """DeviceError naming ``call`` unless ``code`` is 0 or 'has a warning'."""
        if code in (0, _HAS_WARNING):
            return
        codes = self._read_codes() if code == _HAS_ERROR else None
        if codes is not None and codes[0]:
            fault = self._note_error(codes[0])
            raise self._error(f"{call}: controller error {fault[1]} (code {fault[0]})")
        raise self._error(f"{call} failed: {_sdk_code(code)}")

    def _error(self, message: str) -> DeviceError:
        self.errors += 1
        return DeviceError(f"{self.where}: {message}")

    def _servo_error(self, message: str, sent: np.ndarray | None) -> ServoCommandError:
        self.errors += 1
        return ServoCommandError(f"{self.where}: {message}", None if sent is None else sent.copy())


class _ModeReminderFilter(logging.Filter):
    """Drops the SDK's "mode may be incorrect" warning: with reports off, the SDK's copy of the
    mode (fed only by the report stream) stays 0, so it would log this on every servo_j."""

    def filter(self, record: logging.LogRecord) -> bool:
        if str(record.msg).startswith("The mode may be incorrect"):
            return False
        # The SDK's own error lines (``API -> set_servo_angle_j -> code=3, angles=[...]``, "xArm
        # is not connected") say again what this driver raises as one line naming what to
        # check: shown only with debug logging (``--debug``).
        return record.levelno < logging.ERROR or logging.getLogger("beavr_sim").isEnabledFor(
            logging.DEBUG
        )


class _Stderr:
    """A stream that writes to whatever ``sys.stderr`` is at the time of the write."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


_STDERR = _Stderr()


def _print_to_stderr(*args: Any, **kwargs: Any) -> None:
    """``print`` for the SDK's modules: to stderr unless a file is named."""
    if kwargs.get("file") is None:
        kwargs["file"] = _STDERR
    print(*args, **kwargs)


def _sdk_output_to_stderr() -> None:
    """The SDK prints (``SDK_VERSION ...`` on import, ``ROBOT_IP ...`` on connect) and logs
    (``[motion_enable] ...``, through handlers on stdout) where our commands print their JSON
    summary: send all of it to stderr. Only the SDK's own modules and loggers change;
    idempotent."""
    with contextlib.redirect_stdout(_STDERR):
        import xarm.wrapper  # noqa: F401  (the SDK prints its version on first import)
    from xarm.core.utils import log as sdk_log

    for name, module in list(sys.modules.items()):
        if module is not None and (name == "xarm" or name.startswith("xarm.")):
            module.print = _print_to_stderr  # the SDK's print() calls look here first
    for sdk_logger in (sdk_log.logger, sdk_log.origin_logger):
        for handler in sdk_logger.handlers:
            if isinstance(handler, logging.StreamHandler) and handler.stream is not _STDERR:
                handler.setStream(_STDERR)


def _quiet_mode_reminder() -> None:
    from xarm.core.utils.log import logger

    if not any(isinstance(f, _ModeReminderFilter) for f in logger.filters):
        logger.addFilter(_ModeReminderFilter())


def _quiet_disconnect(api: Any) -> None:
    try:
        api.disconnect()
    except Exception:
        pass
