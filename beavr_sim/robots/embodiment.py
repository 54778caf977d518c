"""Embodiments: one or more arm+hand effectors placed in a scene.

An :class:`EmbodimentSpec` is pure data (which effectors, on which side, where). An
:class:`Embodiment` composes those effectors into a ``mujoco.MjSpec`` and, once the scene is
compiled, binds to the model as a :class:`JointIndex`: the addresses that map the hardware
joint order (arm ``joint1..joint7``, then LEAP motors ``0..15``, per effector) onto the
model's ``qpos``, ``qvel`` and actuators.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from beavr_sim.assets import mjcf_path
from beavr_sim.naming import check_name
from beavr_sim.robots.parts import (
    LEAP_HAND,
    LEAP_ON_XARM7,
    SIDES,
    XARM7,
    ArmModel,
    HandModel,
    HandMount,
)
from beavr_sim.workcell import TABLE_TOP_Z


@dataclass(frozen=True)
class EffectorSpec:
    """One arm with a hand, placed at ``base_pos`` (world, metres) turned ``base_yaw_deg``."""

    name: str
    side: str
    base_pos: tuple[float, float, float]
    base_yaw_deg: float = 0.0
    arm: ArmModel = XARM7
    hand: HandModel = LEAP_HAND
    mount: HandMount = LEAP_ON_XARM7

    def __post_init__(self) -> None:
        check_name("side", self.side, SIDES)
        if not self.name or "/" in self.name:
            raise ValueError(f"effector name must be non-empty without '/', got {self.name!r}")
        if len(self.base_pos) != 3:
            raise ValueError(f"base_pos must have 3 values, got {self.base_pos!r}")

    @property
    def prefix(self) -> str:
        return f"{self.name}/"


@dataclass(frozen=True)
class Effector:
    """The model-level names of one effector (what teleop, IK and the guard address)."""

    name: str
    side: str
    arm_joints: tuple[str, ...]
    hand_joints: tuple[str, ...]
    ee_site: str
    palm_site: str
    fingertip_sites: tuple[str, ...]

    @property
    def joints(self) -> tuple[str, ...]:
        """Arm then hand joint names: the order of this effector's slice of actions."""
        return self.arm_joints + self.hand_joints

    @classmethod
    def from_spec(cls, spec: EffectorSpec) -> Effector:
        p = spec.prefix
        return cls(
            name=spec.name,
            side=spec.side,
            arm_joints=tuple(p + j for j in spec.arm.joints),
            hand_joints=tuple(p + j for j in spec.hand.joints),
            ee_site=p + spec.arm.ee_site,
            palm_site=p + spec.hand.palm_site,
            fingertip_sites=tuple(p + s for s in spec.hand.fingertip_sites),
        )


@dataclass(frozen=True)
class EmbodimentSpec:
    name: str
    effectors: tuple[EffectorSpec, ...]
    description: str = ""

    def __post_init__(self) -> None:
        names = [e.name for e in self.effectors]
        if not names or len(set(names)) != len(names):
            raise ValueError(
                f"{self.name}: effector names must be unique and non-empty, got {names}"
            )


# Arms bolt to the table top at world z = TABLE_TOP_Z (beavr_sim.workcell); +x points away from
# the robot base into the workspace, +y to the robot's left. Bimanual arms stand 0.6 m apart
# (BEAVR's bench).
BIMANUAL_HALF_SPACING = 0.3

EMBODIMENTS: dict[str, EmbodimentSpec] = {
    "xarm7_leap_right": EmbodimentSpec(
        "xarm7_leap_right",
        (EffectorSpec("right", "right", (0.0, 0.0, TABLE_TOP_Z)),),
        "one xArm7 with a right LEAP hand",
    ),
    "xarm7_leap_left": EmbodimentSpec(
        "xarm7_leap_left",
        (EffectorSpec("left", "left", (0.0, 0.0, TABLE_TOP_Z)),),
        "one xArm7 with a left LEAP hand",
    ),
    "xarm7_leap_bimanual": EmbodimentSpec(
        "xarm7_leap_bimanual",
        (
            EffectorSpec("left", "left", (0.0, BIMANUAL_HALF_SPACING, TABLE_TOP_Z)),
            EffectorSpec("right", "right", (0.0, -BIMANUAL_HALF_SPACING, TABLE_TOP_Z)),
        ),
        "two xArm7s side by side, left and right LEAP hands",
    ),
}
DEFAULT_EMBODIMENT = "xarm7_leap_right"


def _yaw_quat(deg: float) -> np.ndarray:
    half = np.deg2rad(deg) / 2
    return np.array([np.cos(half), 0.0, 0.0, np.sin(half)])


@dataclass(frozen=True)
class JointIndex:
    """Addresses of an embodiment's joints in a compiled model, in action order."""

    names: tuple[str, ...]
    qpos_adr: np.ndarray
    qvel_adr: np.ndarray
    actuator_ids: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    home: np.ndarray
    slices: dict[str, slice] = field(default_factory=dict)

    @property
    def size(self) -> int:
        return len(self.names)


class Embodiment:
    """Composes effectors into a scene spec and binds them to the compiled model."""

    def __init__(self, spec: EmbodimentSpec):
        self.spec = spec
        self.effectors: list[Effector] = [Effector.from_spec(e) for e in spec.effectors]

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j for e in self.effectors for j in e.joints)

    def effector(self, name: str) -> Effector:
        by_name = {e.name: e for e in self.effectors}
        return by_name[check_name("effector", name, by_name)]

    def attach_to(self, scene: mujoco.MjSpec) -> None:
        """Add every arm (at its base pose) and its hand (on the flange) to ``scene``."""
        for spec in self.spec.effectors:
            arm = mujoco.MjSpec.from_file(str(mjcf_path(spec.arm.mjcf)))
            base = scene.worldbody.add_frame(
                pos=list(spec.base_pos), quat=list(_yaw_quat(spec.base_yaw_deg))
            )
            scene.attach(arm, prefix=spec.prefix, frame=base)
            hand = mujoco.MjSpec.from_file(str(mjcf_path(spec.hand.mjcf(spec.side))))
            flange = scene.site(spec.prefix + spec.arm.ee_site)
            mount = flange.parent.add_frame(
                pos=list(np.add(flange.pos, spec.mount.pos)),
                quat=list(_quat_mul(np.asarray(flange.quat, float), spec.mount.quat(spec.side))),
            )
            scene.attach(hand, prefix=spec.prefix, frame=mount)

    def home(self) -> np.ndarray:
        """Home joint positions in action order (arm home of each side, hand open)."""
        return np.concatenate(
            [np.r_[s.arm.home(s.side), s.hand.home] for s in self.spec.effectors]
        ).astype(np.float64)

    def bind(self, model: mujoco.MjModel) -> JointIndex:
        names = self.joint_names
        qpos_adr, qvel_adr, act_ids, lower, upper = [], [], [], [], []
        act_by_joint = {
            int(model.actuator_trnid[a, 0]): a
            for a in range(model.nu)
            if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
        }
        for n in names:
            j = model.joint(n).id
            if j not in act_by_joint:
                raise ValueError(f"joint {n!r} has no actuator in the compiled model")
            qpos_adr.append(model.jnt_qposadr[j])
            qvel_adr.append(model.jnt_dofadr[j])
            act_ids.append(act_by_joint[j])
            lower.append(model.jnt_range[j, 0])
            upper.append(model.jnt_range[j, 1])
        slices, start = {}, 0
        for e in self.effectors:
            slices[e.name] = slice(start, start + len(e.joints))
            start += len(e.joints)
        return JointIndex(
            names=names,
            qpos_adr=np.array(qpos_adr),
            qvel_adr=np.array(qvel_adr),
            actuator_ids=np.array(act_ids),
            lower=np.array(lower),
            upper=np.array(upper),
            home=self.home(),
            slices=slices,
        )


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, a / np.linalg.norm(a), b)
    return out


def make_embodiment(name: str) -> Embodiment:
    """The embodiment called ``name``; raises with the valid names if it is unknown."""
    return Embodiment(EMBODIMENTS[check_name("embodiment", name, EMBODIMENTS)])
