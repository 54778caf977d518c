"""The robot file: a robot described in TOML, parsed into frozen dataclasses (no MuJoCo here).

A robot file names one or two arms (each from its own MJCF or URDF, paths relative to the
file), a hand per effector (the built-in LEAP hand, or a ``[hands.NAME]`` table: a hand from
its own MJCF, :class:`HandFile`), the mount (flange -> hand), the sides and where each arm
stands at the table. :func:`read_robot_file` parses and checks it; every error names the file, the key
and, for a choice, the valid values. :mod:`beavr_sim.robots.from_file` turns the result into an
:class:`~beavr_sim.robots.embodiment.EmbodimentSpec`; ``docs/robots.md`` documents the format::

    name = "franka_leap_right"
    description = "a Franka Panda with a right LEAP hand"

    [arms.panda]
    model = "panda/chain.xml"               # MJCF, URDF, or a <mujocoinclude> fragment
    fragments = ["panda/assets.xml"]        # fragments included before it (assets, defaults)
    asset_root = "panda"                    # folder the model's meshdir is relative to
    base_body = "panda0_link0"
    flange = { body = "panda0_link7", pos = [0.0, 0.0, 0.107] }   # or { site = "..." }
    joints = ["joint1", "joint2", ...]      # hardware order; limits come from the model
    home_deg = [0, -30, 0, -130, 0, 100, 45]
    max_velocity_deg_s = 120.0
    remove_bodies = ["leftfinger", "rightfinger"]   # a stock gripper
    remove_meshes = ["hand_viz", "hand_col"]

    [[effectors]]
    name = "right"
    side = "right"
    arm = "panda"
    hand = "leap"
    base_pos = [0.0, 0.0, 0.0]              # metres, table frame: z = 0 on the table top
    mount = { pos = [0.0, 0.0, 0.0], yaw_deg = 0.0 }

A hand table (read by :func:`read_hand_table`; its model is checked by
:func:`beavr_sim.robots.hand_file.load_hand`)::

    [hands.shadow]
    model = "shadow/hand.xml"
    root = "palm"                           # the palm body: the hand is its subtree
    palm_axes = ["y", "-x", "z"]            # the root's axes as human palm axes
    servo = { kp = 2.0 }                    # the twin's servos on the hand joints
    [hands.shadow.fingers]
    thumb = "site:thtip"                    # a fingertip site (or "body:NAME") per finger

A path may also be ``pkg://<python package>/<path inside it>``: the file ships inside an
installed (or unpacked) package and is found without importing it.
"""

from __future__ import annotations

import importlib.util
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from beavr_sim.naming import check_name

SIDES = ("right", "left")
#: Hands a robot file can name besides its own ``[hands.NAME]`` tables.
BUILTIN_HANDS = ("leap",)
#: Finger names a hand or a human hand may have, human order.
FINGER_NAMES = ("thumb", "index", "middle", "ring", "little")
#: Fingertip kinds of a ``[hands.NAME.fingers]`` entry: a site, or a body's origin.
TIP_KINDS = ("site", "body")
_AXES = ("x", "y", "z", "-x", "-y", "-z")
#: Suffixes of the model files MuJoCo's compiler reads.
MODEL_SUFFIXES = (".xml", ".mjcf", ".urdf")
PACKAGE_SCHEME = "pkg://"

_TOP_KEYS = ("name", "description", "arms", "hands", "effectors", "guard_box", "workspace")
_ARM_KEYS = (
    "model", "fragments", "asset_root", "base_body", "flange", "joints", "home_deg",
    "home_deg_by_side", "max_velocity_deg_s", "max_acceleration_rad_s2", "remove_bodies",
    "remove_meshes", "upper_arm_links", "forearm_links", "servo", "gravity_compensation",
    "limits_deg",
)  # fmt: skip
_FLANGE_KEYS = ("body", "site", "pos")
_SERVO_KEYS = ("kp", "kv", "force_limit")
_EFFECTOR_KEYS = ("name", "side", "arm", "hand", "base_pos", "base_yaw_deg", "mount")
_MOUNT_KEYS = ("pos", "yaw_deg")
_HAND_KEYS = ("model", "root", "palm_axes", "fingers", "thumb", "human_fingers", "joints",
              "home_deg", "max_velocity_deg_s", "servo")  # fmt: skip


class RobotFileError(ValueError):
    """A robot file that cannot be used: the message names the file and the key."""


@dataclass(frozen=True)
class Flange:
    """Where the hand mounts: a site of the model, or a point (``pos``, body frame) on a body
    whose +z points out of the flange."""

    body: str = ""
    site: str = ""
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ServoGains:
    """The position servos the twin gives the arm's joints: stiffness ``kp`` (N m/rad), damping
    ``kv`` (N m s/rad; default ``kp / 10``) and torque cap ``force_limit`` (N m; 0: the
    model's ``actuatorfrcrange`` where it has one, else none)."""

    kp: float = 1000.0
    kv: float = 0.0
    force_limit: float = 0.0

    @property
    def damping(self) -> float:
        return self.kv if self.kv > 0 else self.kp / 10


#: The position servos of a model-file hand's joints unless its ``servo`` says otherwise:
#: about the LEAP hand's stiffness (1.6 N m/rad), damped with ``kp / 10``.
HAND_SERVO = ServoGains(kp=2.0)


@dataclass(frozen=True)
class HandFile:
    """One ``[hands.NAME]`` table, checked against the file's grammar (not yet the model:
    :func:`beavr_sim.robots.hand_file.load_hand` does that)."""

    name: str
    model: Path
    root: str
    palm_axes: tuple[str, str, str]
    fingers: tuple[tuple[str, str, str], ...]  # (finger, "site" | "body", model name)
    thumb: str
    human_fingers: tuple[tuple[str, str], ...]  # (hand finger, human finger)
    joints: tuple[str, ...] | None
    home_deg: tuple[float, ...] | None
    max_velocity_deg_s: float = 180.0
    servo: ServoGains = HAND_SERVO


def palm_rotation(axes: tuple[str, ...]) -> list[list[float]]:
    """Rows: the root frame's x, y, z as signed human-palm axes; raises on a non-rotation."""
    R = [[0.0] * 3 for _ in range(3)]
    for row, axis in enumerate(axes):
        R[row]["xyz".index(axis[-1])] = -1.0 if axis.startswith("-") else 1.0
    (a, b, c), (d, e, f), (g, h, i) = R
    if round(a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)) != 1:
        raise ValueError(f"palm_axes {list(axes)} is not a right-handed rotation")
    return R


@dataclass(frozen=True)
class ArmFile:
    """One ``[arms.NAME]`` table (see the module docstring)."""

    name: str
    model: Path
    base_body: str
    flange: Flange
    joints: tuple[str, ...]
    home_deg: tuple[float, ...]
    fragments: tuple[Path, ...] = ()
    asset_root: Path | None = None
    home_deg_by_side: dict[str, tuple[float, ...]] = field(default_factory=dict)
    max_velocity_deg_s: float = 120.0
    max_acceleration_rad_s2: float = 150.0
    remove_bodies: tuple[str, ...] = ()
    remove_meshes: tuple[str, ...] = ()
    upper_arm_links: tuple[str, ...] | None = None
    forearm_links: tuple[str, ...] | None = None
    servo: ServoGains = ServoGains()
    gravity_compensation: bool = True
    limits_deg: dict[str, tuple[float, float]] = field(default_factory=dict)

    def home(self, side: str) -> tuple[float, ...]:
        """The home pose (degrees) on ``side``."""
        return self.home_deg_by_side.get(side, self.home_deg)


@dataclass(frozen=True)
class MountFile:
    """The flange -> hand transform: the hand's mount frame ``pos`` (m, flange frame) from the
    flange, turned ``yaw_deg`` about the flange's +z."""

    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class EffectorFile:
    """One ``[[effectors]]`` entry: an arm of ``arms`` on a side, with a hand, at the table."""

    name: str
    side: str
    arm: str
    hand: str = "leap"
    base_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_yaw_deg: float = 0.0
    mount: MountFile = MountFile()


@dataclass(frozen=True)
class RobotFile:
    """A parsed robot file: its path, label, arms and effectors."""

    path: Path
    name: str
    description: str
    arms: dict[str, ArmFile]
    effectors: tuple[EffectorFile, ...]
    guard_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    workspace: tuple[tuple[float, float], tuple[float, float]] | None = None
    hands: dict[str, HandFile] = field(default_factory=dict)


def is_robot_file(name: object) -> bool:
    """Whether ``name`` names a robot file (ends in ``.toml``), existing or not."""
    return isinstance(name, str | Path) and str(name).endswith(".toml")


def resolve_path(text: str, folder: Path) -> Path:
    """A model path of a robot file: ``pkg://package/rest`` inside an importable package (found
    without importing it), else relative to ``folder`` (the robot file's)."""
    if text.startswith(PACKAGE_SCHEME):
        package, _, rest = text[len(PACKAGE_SCHEME) :].partition("/")
        spec = importlib.util.find_spec(package) if package.isidentifier() else None
        if spec is None or not spec.submodule_search_locations:
            raise FileNotFoundError(
                f"{text}: no Python package {package!r} is installed (pip install it, or put "
                "an unpacked copy on PYTHONPATH)"
            )
        return Path(next(iter(spec.submodule_search_locations))) / rest
    return (folder / text).resolve()


def read_robot_file(path: str | Path) -> RobotFile:
    """Parse and check the robot file at ``path``; raises :class:`RobotFileError` naming the
    file and key, or ``FileNotFoundError`` for a missing file."""
    path = Path(path).resolve()
    if not path.is_file():
        raise FileNotFoundError(f"robot file {path} does not exist")
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise RobotFileError(f"{path}: not valid TOML: {e}") from e
    return _Reader(path).robot(data)


def read_hand_table(path: str | Path, name: str, table: Any) -> HandFile:
    """Check one ``[hands.NAME]`` table of the robot file at ``path``."""
    return _Reader(Path(path)).hand(name, table)


class _Reader:
    """Reads one file's tables, naming ``path`` and the key in every error."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, message: str) -> RobotFileError:
        return RobotFileError(f"{self.path}: {where}: {message}")

    def keys(self, table: dict[str, Any], valid: tuple[str, ...], where: str) -> None:
        for key in table:
            if key not in valid:
                raise self.fail(where, f"unknown key {key!r}; valid keys: {', '.join(valid)}")

    def get(self, table: dict[str, Any], key: str, kind: type, where: str, default: Any = ...):
        if key not in table:
            if default is ...:
                raise self.fail(where, f"missing key {key!r}")
            return default
        value = table[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is float and not math.isfinite(value)):
            raise self.fail(f"{where}.{key}", f"expected {kind.__name__}, got {value!r}")
        return value

    def floats(self, table, key, where, n: int | None = None, default: Any = ...):
        if key not in table and default is not ...:
            return default
        values = self.get(table, key, list, where)
        if not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in values
        ) or (n is not None and len(values) != n):
            count = f"{n} " if n is not None else ""
            raise self.fail(f"{where}.{key}", f"expected a list of {count}numbers, got {values!r}")
        return tuple(float(v) for v in values)

    def names(self, table, key, where, default: Any = ...) -> tuple[str, ...]:
        if key not in table and default is not ...:
            return default
        values = self.get(table, key, list, where)
        if not all(isinstance(v, str) and v for v in values):
            raise self.fail(f"{where}.{key}", f"expected a list of names, got {values!r}")
        return tuple(values)

    def file(self, text: str, where: str) -> Path:
        try:
            path = resolve_path(text, self.path.parent)
        except FileNotFoundError as e:
            raise self.fail(where, str(e)) from e
        if not path.exists():
            raise self.fail(where, f"{path} does not exist")
        return path

    def robot(self, data: dict[str, Any]) -> RobotFile:
        self.keys(data, _TOP_KEYS, "top level")
        name = self.get(data, "name", str, "top level")
        arms_table = self.get(data, "arms", dict, "top level")
        if not arms_table:
            raise self.fail("arms", "no arm: add an [arms.NAME] table")
        arms = {key: self.arm(key, table) for key, table in arms_table.items()}
        hands = {
            key: self.hand(key, table)
            for key, table in self.get(data, "hands", dict, "top level", {}).items()
        }
        entries = self.get(data, "effectors", list, "top level")
        if not 1 <= len(entries) <= 2:
            raise self.fail("effectors", f"expected one or two [[effectors]], got {len(entries)}")
        effectors = tuple(self.effector(i, e, arms, hands) for i, e in enumerate(entries))
        for kind, values in (("name", [e.name for e in effectors]),
                             ("side", [e.side for e in effectors])):  # fmt: skip
            if len(set(values)) != len(values):
                raise self.fail("effectors", f"each effector needs its own {kind}, got {values}")
        guard_box = None
        if "guard_box" in data:
            box = self.get(data, "guard_box", list, "top level")
            if len(box) != 2:
                raise self.fail("guard_box", "expected [[x0, y0, z0], [x1, y1, z1]]")
            guard_box = tuple(
                self.floats({corner: c}, corner, "guard_box", 3)
                for corner, c in zip(("lower", "upper"), box, strict=True)
            )
        workspace = None
        if "workspace" in data:
            ws = self.get(data, "workspace", list, "top level")
            if len(ws) != 2:
                raise self.fail("workspace", "expected [[x0, x1], [y0, y1]]")
            workspace = tuple(
                self.floats({axis: r}, axis, "workspace", 2)
                for axis, r in zip("xy", ws, strict=True)
            )
        return RobotFile(
            path=self.path,
            name=name,
            description=self.get(data, "description", str, "top level", ""),
            arms=arms,
            effectors=effectors,
            guard_box=guard_box,  # type: ignore[arg-type]
            workspace=workspace,  # type: ignore[arg-type]
            hands=hands,
        )

    def arm(self, name: str, table: Any) -> ArmFile:
        where = f"arms.{name}"
        if not isinstance(table, dict):
            raise self.fail(where, "expected a table")
        self.keys(table, _ARM_KEYS, where)
        model = self.file(self.get(table, "model", str, where), f"{where}.model")
        if model.suffix.lower() not in MODEL_SUFFIXES:
            raise self.fail(
                f"{where}.model", f"{model.name}: expected one of {', '.join(MODEL_SUFFIXES)}"
            )
        flange_table = self.get(table, "flange", dict, where)
        self.keys(flange_table, _FLANGE_KEYS, f"{where}.flange")
        flange = Flange(
            body=self.get(flange_table, "body", str, f"{where}.flange", ""),
            site=self.get(flange_table, "site", str, f"{where}.flange", ""),
            pos=self.floats(flange_table, "pos", f"{where}.flange", 3, (0.0, 0.0, 0.0)),
        )
        if bool(flange.body) == bool(flange.site):
            raise self.fail(f"{where}.flange", "give exactly one of 'body' or 'site'")
        joints = self.names(table, "joints", where)
        if len(set(joints)) != len(joints):
            raise self.fail(f"{where}.joints", f"joints repeat: {list(joints)}")
        home = self.floats(table, "home_deg", where, len(joints))
        by_side = {}
        for side, values in self.get(table, "home_deg_by_side", dict, where, {}).items():
            check = f"{where}.home_deg_by_side"
            if side not in SIDES:
                raise self.fail(check, f"unknown side {side!r}; valid sides: {', '.join(SIDES)}")
            by_side[side] = self.floats({side: values}, side, check, len(joints))
        limits = {}
        for joint, values in self.get(table, "limits_deg", dict, where, {}).items():
            if joint not in joints:
                raise self.fail(
                    f"{where}.limits_deg", f"{joint!r} is not one of the joints {list(joints)}"
                )
            lo, hi = self.floats({joint: values}, joint, f"{where}.limits_deg", 2)
            if not lo < hi:
                raise self.fail(f"{where}.limits_deg.{joint}", "expected lower < upper")
            limits[joint] = (lo, hi)
        servo = self.servo(table, where, ServoGains())
        arm = ArmFile(
            name=name,
            model=model,
            base_body=self.get(table, "base_body", str, where),
            flange=flange,
            joints=joints,
            home_deg=home,
            fragments=tuple(
                self.file(f, f"{where}.fragments")
                for f in self.names(table, "fragments", where, ())
            ),
            asset_root=(
                self.file(self.get(table, "asset_root", str, where), f"{where}.asset_root")
                if "asset_root" in table
                else None
            ),
            home_deg_by_side=by_side,
            max_velocity_deg_s=self.get(table, "max_velocity_deg_s", float, where, 120.0),
            max_acceleration_rad_s2=self.get(table, "max_acceleration_rad_s2", float, where, 150.0),
            remove_bodies=self.names(table, "remove_bodies", where, ()),
            remove_meshes=self.names(table, "remove_meshes", where, ()),
            upper_arm_links=self.names(table, "upper_arm_links", where, None),
            forearm_links=self.names(table, "forearm_links", where, None),
            servo=servo,
            gravity_compensation=self.get(table, "gravity_compensation", bool, where, True),
            limits_deg=limits,
        )
        for key in ("max_velocity_deg_s", "max_acceleration_rad_s2"):
            if not getattr(arm, key) > 0:
                raise self.fail(f"{where}.{key}", f"must be positive, got {getattr(arm, key)}")
        return arm

    def servo(self, table: dict[str, Any], where: str, default: ServoGains) -> ServoGains:
        servo_table = self.get(table, "servo", dict, where, {})
        self.keys(servo_table, _SERVO_KEYS, f"{where}.servo")
        values = {k: self.get(servo_table, k, float, f"{where}.servo") for k in servo_table}
        servo = ServoGains(**{**default.__dict__, **values})
        if not servo.kp > 0 or servo.kv < 0 or servo.force_limit < 0:
            raise self.fail(f"{where}.servo", "kp must be positive, kv and force_limit >= 0")
        return servo

    def hand(self, name: str, table: Any) -> HandFile:
        where = f"hands.{name}"
        if name in BUILTIN_HANDS:
            raise self.fail(where, f"{name!r} is a built-in hand: give this table another name")
        if not isinstance(table, dict):
            raise self.fail(where, "expected a table")
        self.keys(table, _HAND_KEYS, where)
        axes = self.names(table, "palm_axes", where, ("x", "y", "z"))
        if len(axes) != 3 or any(a not in _AXES for a in axes):
            raise self.fail(
                f"{where}.palm_axes", f"expected 3 of {', '.join(_AXES)}, got {list(axes)}"
            )
        try:
            palm_rotation(axes)
        except ValueError as e:
            raise self.fail(f"{where}.palm_axes", str(e)) from None
        finger_table = self.get(table, "fingers", dict, where)
        if not finger_table:
            raise self.fail(
                f"{where}.fingers", f"no finger; valid fingers: {', '.join(FINGER_NAMES)}"
            )
        fingers = []
        for finger, text in finger_table.items():
            key = f"{where}.fingers.{finger}"
            try:
                check_name("finger", finger, FINGER_NAMES)
            except ValueError as e:
                raise self.fail(key, str(e)) from None
            kind, sep, target = text.partition(":") if isinstance(text, str) else ("", "", "")
            if not sep or kind not in TIP_KINDS or not target:
                raise self.fail(key, f"expected 'site:NAME' or 'body:NAME', got {text!r}")
            fingers.append((finger, kind, target))
        names = [f for f, _, _ in fingers]
        thumb = self.get(table, "thumb", str, where, "thumb")
        try:
            check_name("thumb", thumb, names)
        except ValueError as e:
            raise self.fail(f"{where}.thumb", str(e)) from None
        human_table = self.get(table, "human_fingers", dict, where, {})
        for finger, human in human_table.items():
            try:
                check_name("hand finger", finger, names)
                check_name("human finger", human, FINGER_NAMES)
            except ValueError as e:
                raise self.fail(f"{where}.human_fingers.{finger}", str(e)) from None
        velocity = self.get(table, "max_velocity_deg_s", float, where, 180.0)
        if not velocity > 0:
            raise self.fail(f"{where}.max_velocity_deg_s", f"must be positive, got {velocity}")
        joints = self.names(table, "joints", where, None)
        if joints is not None and len(set(joints)) != len(joints):
            raise self.fail(f"{where}.joints", f"joints repeat: {list(joints)}")
        return HandFile(
            name=name,
            model=self.file(self.get(table, "model", str, where), f"{where}.model"),
            root=self.get(table, "root", str, where),
            palm_axes=axes,  # type: ignore[arg-type]
            fingers=tuple(fingers),
            thumb=thumb,
            human_fingers=tuple((f, human_table.get(f, f)) for f in names),
            joints=joints,
            home_deg=self.floats(table, "home_deg", where, len(joints) if joints else None, None),
            max_velocity_deg_s=velocity,
            servo=self.servo(table, where, HAND_SERVO),
        )

    def effector(
        self, index: int, table: Any, arms: dict[str, ArmFile], hands: dict[str, HandFile]
    ) -> EffectorFile:
        where = f"effectors[{index}]"
        if not isinstance(table, dict):
            raise self.fail(where, "expected a table")
        self.keys(table, _EFFECTOR_KEYS, where)
        name = self.get(table, "name", str, where)
        if not name or "/" in name or name == "body":
            raise self.fail(f"{where}.name", f"expected a name without '/' (not 'body'): {name!r}")
        choices = {
            "side": (self.get(table, "side", str, where), SIDES),
            "arm": (self.get(table, "arm", str, where), tuple(arms)),
            "hand": (self.get(table, "hand", str, where, "leap"), BUILTIN_HANDS + tuple(hands)),
        }
        for key, (value, valid) in choices.items():
            try:
                check_name(key, value, valid)
            except ValueError as e:
                raise self.fail(f"{where}.{key}", str(e)) from None
        mount_table = self.get(table, "mount", dict, where, {})
        self.keys(mount_table, _MOUNT_KEYS, f"{where}.mount")
        return EffectorFile(
            name=name,
            side=choices["side"][0],
            arm=choices["arm"][0],
            hand=choices["hand"][0],
            base_pos=self.floats(table, "base_pos", where, 3, (0.0, 0.0, 0.0)),  # type: ignore[arg-type]
            base_yaw_deg=self.get(table, "base_yaw_deg", float, where, 0.0),
            mount=MountFile(
                pos=self.floats(mount_table, "pos", f"{where}.mount", 3, (0.0, 0.0, 0.0)),  # type: ignore[arg-type]
                yaw_deg=self.get(mount_table, "yaw_deg", float, f"{where}.mount", 0.0),
            ),
        )
