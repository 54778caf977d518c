"""A rig: which devices mirror the twin, the effector each serves, and how the mirror behaves.

A rig file (``--hardware-config F.toml``, read with :mod:`tomllib`)::

    [mirror]                      # optional; see MirrorConfig (defaults shown)
    arm_divergence_rad = 0.3      # measured vs sent (rad), for longer than ...
    hand_divergence_rad = 0.8
    divergence_window_s = 0.5     # ... this (s): the device holds until released
    device_lag_s = 0.25           # measured joints judged against targets sent this recently
    command_timeout_s = 0.25      # no fresh command this long (s): hold, resume on the next
    arm_catch_up_speed = 0.5      # rad/s after a hold, a release, a reset (guarded)
    hand_catch_up_speed = 1.5
    reconnect_s = 5.0             # a device that stops answering is retried this long (s)
    arm_sync_tolerance_rad = 0.05 # in sync (an episode may start): measured vs twin (rad)
    hand_sync_tolerance_rad = 0.2
    sync_timeout_s = 30.0         # the longest a session waits for sync before an episode

    [[devices]]
    name = "right_arm"            # unique in the rig
    kind = "xarm7"                # xarm7 (the arm's 7 joints) | leap (the hand's 16)
    effector = "right"            # an effector of the embodiment
    host = "192.168.1.185"        # the rest are the device's config (XArmConfig, LeapHandConfig)

    [[devices]]
    name = "right_hand"
    kind = "leap"
    effector = "right"
    port = "/dev/ttyUSB0"

The RX-1 (``--embodiment rx1``) runs on Feetech STS3215 servos, one bus per servo group::

    [[devices]]
    name = "rx1_right_arm"
    kind = "feetech"
    effector = "right"            # group right_arm (ids 11-17)
    group = "right_arm"
    port = "/dev/ttyUSB1"

    [[devices]]
    name = "rx1_body"
    kind = "feetech"
    effector = "body"             # the torso and head (ids 1-6): they hold their pose
    group = "body"
    port = "/dev/ttyUSB0"

``--hardware-config emulated`` starts a protocol emulator for every device of the embodiment
(:class:`EmulatedRig`) so mirroring can be tried with no robot. Examples for the paper's three
configurations are in ``docs/hardware.md``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import threading
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from beavr_sim.hardware.device import Device
from beavr_sim.hardware.faults import FaultSpec, parse_fault_spec, parse_fault_specs
from beavr_sim.hardware.feetech.config import (
    GROUPS,
    RX1_ANGLE_LIMITS,
    FeetechConfig,
    allowed_counts,
    angle_to_counts,
)
from beavr_sim.hardware.feetech.driver import FeetechBus
from beavr_sim.hardware.leap.config import LeapHandConfig, model_to_counts
from beavr_sim.hardware.leap.driver import LeapHand
from beavr_sim.hardware.xarm.config import XArmConfig
from beavr_sim.hardware.xarm.driver import XArm7
from beavr_sim.naming import check_name
from beavr_sim.robots.embodiment import BODY_PREFIX, Embodiment, JointIndex

#: Device kinds, the config class of each and the part of an effector it drives (a Feetech
#: bus: its servo group's part, :data:`FEETECH_GROUP_PART`).
DEVICE_KINDS: dict[str, tuple[type, str | None]] = {
    "xarm7": (XArmConfig, "arm"),
    "leap": (LeapHandConfig, "hand"),
    "feetech": (FeetechConfig, None),
}
#: An RX-1 servo group -> the part it drives: an effector's arm, or the body (effector
#: ``"body"``, the torso and head).
FEETECH_GROUP_PART = {
    "right_arm": "arm",
    "left_arm": "arm",
    "body": "body",
    "torso": "body",
    "head": "body",
}
#: The effector name of a device that drives the body.
BODY = BODY_PREFIX.rstrip("/")
#: Each arm model's device kind (what ``--hardware-config emulated`` emulates).
ARM_DEVICE_KIND = {"xarm7": "xarm7", "rx1_arm": "feetech"}
_RESERVED = ("name", "kind", "effector")


@dataclass(frozen=True)
class MirrorConfig:
    """How the hardware follows the twin (see :mod:`beavr_sim.hardware.mirror`). Every field
    is a positive number of the unit its comment names."""

    #: A device's measured joints may differ from what it was sent (within its lag) by this
    #: much (rad) ...
    arm_divergence_rad: float = 0.3
    #: (fingers: they stop on what they grasp, where their targets go on) ...
    hand_divergence_rad: float = 0.8
    #: ... for at most this long (s) before the device holds.
    divergence_window_s: float = 0.5
    #: How far behind its targets (s) a device may be: its measured joints are judged against
    #: every target sent within this time.
    device_lag_s: float = 0.25
    #: A device holds when no fresh command came for this long (s); it resumes when they come.
    command_timeout_s: float = 0.25
    #: Speed (rad/s) at which a device catches up with the twin after a hold, a release or a
    #: reset (the twin jumps home, the hardware moves there slowly, guarded).
    arm_catch_up_speed: float = 0.5
    hand_catch_up_speed: float = 1.5
    #: A device that stops answering is reconnected for up to this long (s); back within it
    #: and where it was held, it resumes; otherwise it stays failed until re-armed.
    reconnect_s: float = 5.0
    #: In sync (an episode may start; a reconnected device is where it was held): every
    #: measured joint within this much (rad) of the twin's ...
    arm_sync_tolerance_rad: float = 0.05
    hand_sync_tolerance_rad: float = 0.2
    #: ... and the longest (s) a session waits for that before an episode (else a hardware
    #: fault).
    sync_timeout_s: float = 30.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"mirror.{f.name} must be a number, got {value!r}")
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(
                    f"mirror.{f.name} must be a positive, finite number, got {value!r}"
                )
        for name in ("reconnect_s", "sync_timeout_s"):
            if getattr(self, name) > 3600:
                raise ValueError(
                    f"mirror.{name} must be at most 3600 s, got {getattr(self, name)!r}"
                )
        for part in ("arm", "hand"):
            tolerance = getattr(self, f"{part}_sync_tolerance_rad")
            limit = getattr(self, f"{part}_divergence_rad")
            if tolerance > limit:
                raise ValueError(
                    f"mirror.{part}_sync_tolerance_rad ({tolerance!r}) must not exceed "
                    f"mirror.{part}_divergence_rad ({limit!r}): a device in sync is not diverged"
                )


@dataclass(frozen=True)
class DeviceEntry:
    """One device of a rig: its name, kind, effector and its own config."""

    name: str
    kind: str
    effector: str
    config: Any

    @property
    def part(self) -> str:
        """``"arm"``, ``"hand"`` or ``"body"``."""
        part = DEVICE_KINDS[self.kind][1]
        return part if part is not None else FEETECH_GROUP_PART[self.config.group]


@dataclass(frozen=True)
class RigConfig:
    devices: tuple[DeviceEntry, ...]
    mirror: MirrorConfig = field(default_factory=MirrorConfig)
    #: Where it came from (a path, or "emulated").
    source: str = ""

    def __post_init__(self) -> None:
        if not self.devices:
            raise ValueError(f"rig {self.source or ''} has no devices".replace("  ", " "))
        names = [d.name for d in self.devices]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"rig device names must be unique, repeated: {duplicates}")
        parts = [(d.effector, d.part) for d in self.devices]
        twice = sorted({p for p in parts if parts.count(p) > 1})
        if twice:
            raise ValueError(f"rig drives the same effector part twice: {twice}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "") -> RigConfig:
        # [cameras.NAME] tables are read by beavr_sim.cameras.spec (LeRobot's camera configs).
        unknown = sorted(set(data) - {"mirror", "devices", "cameras"})
        if unknown:
            raise ValueError(
                f"{source}: unknown tables {unknown}; valid: ['cameras', 'devices', 'mirror']"
            )
        mirror_data = data.get("mirror", {})
        valid = [f.name for f in dataclasses.fields(MirrorConfig)]
        for key in mirror_data:
            check_name("mirror setting", key, valid)
        devices = []
        for i, entry in enumerate(data.get("devices", [])):
            missing = [k for k in _RESERVED if k not in entry]
            if missing:
                raise ValueError(f"{source}: devices[{i}] needs {missing}")
            kind = check_name("device kind", entry["kind"], DEVICE_KINDS)
            config_cls = DEVICE_KINDS[kind][0]
            settings = {k: _tuples(v) for k, v in entry.items() if k not in _RESERVED}
            fields = [f.name for f in dataclasses.fields(config_cls)]
            for key in settings:
                check_name(f"{kind} setting", key, [f for f in fields if f != "name"])
            try:
                config = config_cls(**settings)
            except TypeError as exc:
                raise ValueError(f"{source}: devices[{i}] ({entry['name']}): {exc}") from None
            devices.append(DeviceEntry(str(entry["name"]), kind, str(entry["effector"]), config))
        return cls(tuple(devices), MirrorConfig(**mirror_data), source)

    @classmethod
    def from_toml(cls, path: str | Path) -> RigConfig:
        path = Path(path)
        try:
            with path.open("rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise FileNotFoundError(
                f"rig file {path} not found (pass --hardware-config F.toml, or 'emulated' to "
                "try mirroring with emulated devices; examples in docs/hardware.md)"
            ) from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"rig file {path}: {exc}") from None
        return cls.from_dict(data, str(path))

    def leap_variant(self) -> str | None:
        """The variant (``LeapHandConfig.variant``) of the rig's LEAP hands, None without any.
        The twin models its hands as one variant (their torque cap, docs/models.md), so the
        hands of a mirrored rig must agree: raises if they do not."""
        hands = [d for d in self.devices if d.kind == "leap"]
        variants = {d.config.variant for d in hands}
        if len(variants) > 1:
            each = ", ".join(f"{d.name} {d.config.variant!r}" for d in hands)
            raise ValueError(
                f"rig {self.source}: the LEAP hands are of different variants ({each}); the "
                "twin simulates one variant for all hands: make them all 'full' or all 'lite'"
            )
        return variants.pop() if variants else None

    def check_embodiment(self, embodiment: Embodiment) -> None:
        """Every device serves an effector (or the body) of ``embodiment``, with the servo group
        of that effector's side."""
        names = [e.name for e in embodiment.effectors]
        for d in self.devices:
            if d.part == "body":
                if not embodiment.body_joints:
                    raise ValueError(
                        f"device {d.name} drives a body, but {embodiment.name} has none"
                    )
                if d.effector != BODY:
                    raise ValueError(f"device {d.name} drives the body: effector = {BODY!r}")
                continue
            check_name(f"effector (device {d.name})", d.effector, names)
            if d.kind == "feetech":
                side = embodiment.effector(d.effector).side
                if d.config.group != f"{side}_arm":
                    raise ValueError(
                        f"device {d.name} serves the {side} effector {d.effector!r}: its group "
                        f"must be {side}_arm, got {d.config.group!r}"
                    )


def _tuples(value: Any) -> Any:
    """TOML arrays as tuples (the device configs are frozen dataclasses of tuples)."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


def joint_names_of(entry: DeviceEntry, embodiment: Embodiment) -> tuple[str, ...]:
    """The model joints ``entry`` drives, in the device's order."""
    if entry.part == "body":
        return tuple(BODY_PREFIX + s.joint for s in GROUPS[entry.config.group])
    effector = embodiment.effector(entry.effector)
    return effector.arm_joints if entry.part == "arm" else effector.hand_joints


def build_device(entry: DeviceEntry, embodiment: Embodiment, joints: JointIndex) -> Device:
    """The driver of ``entry``, its joint names (and, for a hand or a Feetech group, limits)
    from the model."""
    names = joint_names_of(entry, embodiment)
    if entry.kind == "xarm7":
        return XArm7(entry.config, name=entry.name, joint_names=names)
    index = [joints.names.index(n) for n in names]
    config = entry.config
    config = dataclasses.replace(
        config,
        name=entry.name,
        joint_names=names,
        lower=config.lower if config.lower is not None else tuple(joints.lower[index]),
        upper=config.upper if config.upper is not None else tuple(joints.upper[index]),
    )
    return FeetechBus(config) if entry.kind == "feetech" else LeapHand(config)


def emulated_device_names(embodiment: Embodiment) -> tuple[str, ...]:
    """The names :class:`EmulatedRig` gives the emulated devices of ``embodiment`` (what fault
    specs name): ``<effector>_arm`` and ``<effector>_hand`` per effector, then ``body`` if it
    has one. For checking ``--emulate-faults`` text before anything starts."""
    names = [f"{e.name}_{part}" for e in embodiment.effectors for part in ("arm", "hand")]
    return (*names, BODY) if embodiment.body_joints else tuple(names)


def _feetech_start(group: str, q: np.ndarray) -> dict:
    servos = GROUPS[group]
    counts = angle_to_counts(
        np.asarray(q, float), [s.direction for s in servos], [s.gear for s in servos]
    )
    # Each servo within what the RX-1's angle limits allow (multi-turn for the geared ones).
    lo, hi = np.array([allowed_counts(*RX1_ANGLE_LIMITS[s.id]) for s in servos]).T
    return {"group": group, "counts": [int(c) for c in np.clip(counts, lo, hi)]}


#: Serial devices of the emulated rig answer from a process on the same (maybe busy) machine,
#: not from a servo's own processor: a reply may wait this long (the SDKs assume ~34 ms), and
#: a connect keeps pinging this long (a rig file's default is 0.5 s).
EMULATED_REPLY_TIMEOUT_S = 0.25
EMULATED_CONNECT_TIMEOUT_S = 5.0


class EmulatedRig:
    """Protocol emulators for every device of an embodiment, and the rig that uses them.

    The emulators run in a child process (``python -m beavr_sim.hardware.emulators``), as a
    real controller and a real bus run outside ours: they do not compete with the drivers for
    this interpreter. The constructor returns once
    every emulator is serving. :meth:`close` stops them and keeps what they received in
    :attr:`received` (``{device: [[time, targets], ...]}``: every servo_j target of an arm;
    every goal write of a hand, ``{motor id: model radians}``).

    Faults (:mod:`beavr_sim.hardware.faults`): ``faults`` (``--emulate-faults`` text, or
    :class:`FaultSpec` s) are in place when the constructor returns, their ``@T`` counted from
    the emulators' start; :meth:`inject` adds more at run time and returns once the child
    acknowledged them. Device names: :attr:`device_names` (``<effector>_arm``,
    ``<effector>_hand``, ``body``).
    """

    def __init__(
        self,
        embodiment: Embodiment,
        joints: JointIndex,
        q_start: np.ndarray | None = None,
        leap_variant: str = "full",
        faults: str | Sequence[FaultSpec] = (),
        keep_received: bool = True,
    ):
        #: Whether :meth:`close` reads back what every emulator received (tests check it; a
        #: session leaves it: after hours the logs are hundreds of MB).
        self.keep_received = keep_received
        q_start = joints.home if q_start is None else np.asarray(q_start, dtype=np.float64)
        plan, groups = [], {}
        for spec, effector in zip(embodiment.spec.effectors, embodiment.effectors, strict=True):
            q = q_start[joints.slices[effector.name]]
            n_arm = len(effector.arm_joints)
            name = f"{effector.name}_arm"
            if ARM_DEVICE_KIND[spec.arm.name] == "feetech":
                groups[name] = f"{spec.side}_arm"
                plan.append([name, "feetech", _feetech_start(groups[name], q[:n_arm])])
            else:
                plan.append([name, "xarm7", [float(v) for v in q[:n_arm]]])
            counts = [int(c) for c in model_to_counts(q[n_arm:])]
            plan.append([f"{effector.name}_hand", "leap", counts])
        if embodiment.body_joints:
            groups[BODY] = "body"
            plan.append([BODY, "feetech", _feetech_start("body", q_start[joints.body])])
        #: The emulated devices' names, as fault specs name them.
        self.device_names: tuple[str, ...] = tuple(name for name, _, _ in plan)
        specs = self._fault_specs(faults)
        self._lock = threading.Lock()
        self._process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "beavr_sim.hardware.emulators",
                json.dumps(plan),
                ",".join(str(s) for s in specs),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        line = self._process.stdout.readline()
        if not line:
            self._process.kill()
            self._process.wait()
            raise RuntimeError("the device emulators did not start (see the error above)")
        where = json.loads(line)
        self.received: dict[str, list] = {}
        #: After :meth:`close`: per device, requests ``lost`` to a freeze or a disconnect and
        #: replies ``dropped`` or ``corrupted`` by the injected faults.
        self.fault_counts: dict[str, dict[str, int]] = {}
        devices = []
        for name, kind, _ in plan:
            effector = name.rsplit("_", 1)[0]
            if kind == "xarm7":
                host, port = where[name]
                config = XArmConfig(host=host, port=port, max_joint_speed=math.pi)
            elif kind == "feetech":
                # The emulated servos' top speed, not the RX-1 driver's calm 1 rad/s.
                config = FeetechConfig(
                    port=where[name],
                    group=groups[name],
                    speed_rad_s=None,
                    reply_timeout_s=EMULATED_REPLY_TIMEOUT_S,
                    timeout_s=EMULATED_CONNECT_TIMEOUT_S,
                )
            else:
                config = LeapHandConfig(
                    port=where[name],
                    variant=leap_variant,
                    reply_timeout_s=EMULATED_REPLY_TIMEOUT_S,
                    timeout_s=EMULATED_CONNECT_TIMEOUT_S,
                )
            devices.append(DeviceEntry(name, kind, effector, config))
        # The mirror's own limits (hand_divergence_rad 0.8, docs/hardware.md): the divergence
        # is measured against what each device was sent, which the emulated servos follow.
        self.config = RigConfig(tuple(devices), MirrorConfig(), "emulated")

    def _fault_specs(self, faults: str | Sequence[FaultSpec]) -> tuple[FaultSpec, ...]:
        if isinstance(faults, str):
            return parse_fault_specs(faults, self.device_names)
        specs = tuple(faults)
        for spec in specs:
            if spec.device not in self.device_names:
                raise ValueError(
                    f"fault {spec}: unknown device {spec.device!r}; devices {list(self.device_names)}"
                )
        return specs

    def inject(self, device_name: str, fault: str | FaultSpec) -> FaultSpec:
        """Put emulated device ``device_name`` under ``fault`` (a :class:`FaultSpec` of that
        device, or its text without the device: ``"freeze=2.5"``, ``"drop=0.05@3"``,
        ``"disconnect"``; ``@T`` counts from now). Returns once the emulators acknowledged it;
        ValueError for a bad fault, RuntimeError when the emulators are gone."""
        if isinstance(fault, str):
            spec = parse_fault_spec(f"{device_name}:{fault}", self.device_names)
        else:
            spec = fault
            if spec.device != device_name:
                raise ValueError(f"fault {spec} is not one of device {device_name!r}")
            self._fault_specs((spec,))
        with self._lock:
            try:
                self._process.stdin.write(f"fault {spec}\n")
                self._process.stdin.flush()
                line = self._process.stdout.readline()
            except (OSError, ValueError):
                line = ""
        if not line:
            raise RuntimeError("the device emulators are gone (closed, or their process died)")
        answer = json.loads(line)
        if "error" in answer:
            raise ValueError(answer["error"])
        return spec

    def close(self) -> None:
        """Stop the emulators (idempotent); what they received lands in :attr:`received`."""
        with self._lock:
            if self._process.poll() is None:
                try:
                    self._process.stdin.write("close\n" if self.keep_received else "close counts\n")
                    self._process.stdin.flush()
                    line = self._process.stdout.readline()
                    if line:
                        self.received = json.loads(line)
                        line = self._process.stdout.readline()
                        self.fault_counts = json.loads(line) if line else {}
                    self._process.wait(10.0)
                except (OSError, ValueError, subprocess.TimeoutExpired):
                    pass
            if self._process.poll() is None:
                self._process.kill()
                self._process.wait()
