"""Embodiments: one or more arm+hand effectors placed in a scene, optionally on a body.

An :class:`EmbodimentSpec` is pure data (which effectors, on which side, where; for a humanoid,
the body that carries the arms). An :class:`Embodiment` composes them into a ``mujoco.MjSpec``
and, once the scene is compiled, binds to the model as a :class:`JointIndex`: the addresses
that map the hardware joint order (per effector: arm joints, then LEAP motors ``0..15``; then
the body's joints) onto the model's ``qpos``, ``qvel`` and actuators.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.assets import mjcf_path
from beavr_sim.naming import check_name
from beavr_sim.robots.from_file import load_robot_file
from beavr_sim.robots.identity import embodiment_label
from beavr_sim.robots.parts import (
    LEAP_ON_RX1,
    RX1_ARM,
    RX1_BODY,
)
from beavr_sim.robots.robot_file import is_robot_file
from beavr_sim.robots.specs import BODY_PREFIX, EffectorSpec, EmbodimentSpec
from beavr_sim.robots.visuals import PART_VISUALS, add_visuals, strip_visuals
from beavr_sim.workcell import TABLE_HALF_Y, TABLE_TOP_Z, TABLE_X


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


#: Height of the RX-1's shoulder sites above its base (URDF: torso 0.5825 + 0.15 + 0.08 + 0.21,
#: shoulder base 0.05 below the head base).
RX1_SHOULDER_HEIGHT = 0.5825 + 0.15 + 0.08 + 0.21 - 0.05

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
    # The RX-1 stands on a 12 cm stand behind the table's near edge (x = -0.25), facing +x:
    # shoulders about 0.42 m above the table top. Objects go 0.34-0.56 m in front of the
    # shoulders, where each hand reaches them palm-down both at the table and 12 cm above it
    # (closer in, the wrist would have to be inside the shoulder to hold a palm-down hand high
    # over an object: the scripted approaches from above fall short and sweep it away).
    "rx1": EmbodimentSpec(
        "rx1",
        (
            EffectorSpec(
                "left",
                "left",
                (-0.42, 0.12, 0.12 + RX1_SHOULDER_HEIGHT),
                arm=RX1_ARM,
                mount=LEAP_ON_RX1,
            ),
            EffectorSpec(
                "right",
                "right",
                (-0.42, -0.12, 0.12 + RX1_SHOULDER_HEIGHT),
                arm=RX1_ARM,
                mount=LEAP_ON_RX1,
            ),
        ),
        "the RX-1 humanoid (torso, head, two 7-DoF arms) with left and right LEAP hands",
        body=RX1_BODY,
        body_pos=(-0.42, 0.0, 0.12),
        workspace=((-0.08, 0.14), (-0.3, 0.3)),
        camera_shift=(-0.5, 0.0, 0.0),
        # From behind the robot's shoulders to the table's far edge; down to 0.25 m below the
        # table top behind its near edge (where the elbows pass), the table itself being an
        # obstacle of the contact rule.
        guard_box=(
            (-0.7, -TABLE_HALF_Y, TABLE_TOP_Z - 0.25),
            (TABLE_X[1], TABLE_HALF_Y, TABLE_TOP_Z + 1.2),
        ),
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
    #: Effector name -> its joints' slice (arm then hand).
    slices: dict[str, slice] = field(default_factory=dict)
    #: The body's joints (torso, head), after every effector's; empty without a body.
    body: slice = slice(0, 0)

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
        """What builds it again: a built-in's name, or a robot file's path."""
        return self.spec.name

    @property
    def label(self) -> str:
        """What summaries and viewers show: a built-in's name, or a robot file's ``name``."""
        return embodiment_label(self.spec.name)

    @property
    def body_joints(self) -> tuple[str, ...]:
        """The body's joint names in the scene (``body/torso_yaw``, ...); empty without one."""
        body = self.spec.body
        return tuple(BODY_PREFIX + j for j in body.joints) if body else ()

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Every effector's joints (arm then hand), then the body's."""
        return tuple(j for e in self.effectors for j in e.joints) + self.body_joints

    @property
    def cameras(self) -> tuple[str, ...]:
        """Cameras the robot carries (e.g. the RX-1's ``head``), named so in the scene."""
        body = self.spec.body
        return tuple(body.cameras) if body else ()

    def effector(self, name: str) -> Effector:
        by_name = {e.name: e for e in self.effectors}
        return by_name[check_name("effector", name, by_name)]

    def attach_to(self, scene: mujoco.MjSpec, visuals: bool = False) -> None:
        """Add the body (if any), every arm (at its base pose, or at the body's site for its
        side) and its hand (on the flange) to ``scene``. ``visuals``: with the parts' visual
        geometry (:mod:`beavr_sim.robots.visuals`; no effect on the physics)."""

        def load(part: str) -> mujoco.MjSpec:
            spec = mujoco.MjSpec.from_file(str(mjcf_path(part)))
            if part in PART_VISUALS:
                if visuals:
                    add_visuals(spec, part)
            elif not visuals:  # a robot file's part carries its own visual geoms
                strip_visuals(spec)
            return spec

        body = self.spec.body
        if body is not None:
            frame = scene.worldbody.add_frame(pos=list(self.spec.body_pos))
            scene.attach(load(body.mjcf), prefix=BODY_PREFIX, frame=frame)
            for camera in body.cameras:  # the robot's cameras keep their own names
                scene.camera(BODY_PREFIX + camera).name = camera
        for spec in self.spec.effectors:
            arm = load(spec.arm.mjcf_for(spec.side))
            if body is not None:
                site = scene.site(BODY_PREFIX + body.arm_sites_by_side[spec.side])
                base = site.parent.add_frame(pos=list(site.pos), quat=list(_site_quat(site)))
            else:
                base = scene.worldbody.add_frame(
                    pos=list(spec.base_pos), quat=list(_yaw_quat(spec.base_yaw_deg))
                )
            scene.attach(arm, prefix=spec.prefix, frame=base)
            hand = load(spec.hand.mjcf(spec.side))
            flange = scene.site(spec.prefix + spec.arm.ee_site)
            pos, quat = (
                np.add(flange.pos, spec.mount.pos),
                _quat_mul(_site_quat(flange), spec.mount.quat(spec.side)),
            )
            if spec.mount.anchor_body:
                # The anchor body lands on the mount pose: the root goes at T_anchor_root.
                pos, quat = _compose(
                    pos, quat, *_inverse(*_body_pose(hand, spec.mount.anchor_body))
                )
            mount = flange.parent.add_frame(pos=list(pos), quat=list(quat))
            scene.attach(hand, prefix=spec.prefix, frame=mount)

    def home(self) -> np.ndarray:
        """Home joint positions in action order (arm home of each side, hand open, then the
        body's held pose)."""
        body = np.asarray(self.spec.body.home if self.spec.body else (), dtype=np.float64)
        return np.concatenate(
            [np.r_[s.arm.home(s.side), s.hand.home] for s in self.spec.effectors] + [body]
        ).astype(np.float64)

    def servo_joints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The action indices of the arm joints whose arm has an :class:`ArmServo` (followed
        by interpolation in the twin), with each one's speed and acceleration cap."""
        index, v_max, a_max, start = [], [], [], 0
        for spec in self.spec.effectors:
            n_arm, n = len(spec.arm.joints), len(spec.arm.joints) + len(spec.hand.joints)
            if spec.arm.servo is not None:
                index.extend(range(start, start + n_arm))
                v_max.extend([spec.arm.servo.max_velocity] * n_arm)
                a_max.extend([spec.arm.servo.max_acceleration] * n_arm)
            start += n
        return np.array(index, dtype=np.int64), np.array(v_max), np.array(a_max)

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
            body=slice(start, len(names)),
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


def _site_quat(site) -> np.ndarray:
    """A spec site's orientation as a unit quaternion, whichever way the file gave it."""
    if site.alt.type == mujoco.mjtOrientation.mjORIENTATION_QUAT:
        return np.asarray(site.quat, float) / np.linalg.norm(site.quat)
    return _euler_quat(np.asarray(site.alt.euler, float))


def _euler_quat(euler: np.ndarray) -> np.ndarray:
    """Intrinsic x-y-z Euler angles (MuJoCo's default ``eulerseq``) -> quaternion."""
    out = np.array([1.0, 0.0, 0.0, 0.0])
    for axis, angle in zip(np.eye(3), euler, strict=True):
        q = np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]
        out = _quat_mul(out, q)
    return out


def _body_pose(spec: mujoco.MjSpec, body: str) -> tuple[np.ndarray, np.ndarray]:
    """Pose of ``body`` in the root frame of the compiled ``spec`` at its zero configuration."""
    model = spec.copy().compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    return data.body(body).xpos.copy(), data.body(body).xquat.copy()


def _inverse(pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q_inv = np.zeros(4)
    mujoco.mju_negQuat(q_inv, quat)
    p_inv = np.zeros(3)
    mujoco.mju_rotVecQuat(p_inv, -np.asarray(pos, float), q_inv)
    return p_inv, q_inv


def _compose(p1, q1, p2, q2) -> tuple[np.ndarray, np.ndarray]:
    """(p1, q1) * (p2, q2): the second pose expressed through the first."""
    p = np.zeros(3)
    mujoco.mju_rotVecQuat(p, np.asarray(p2, float), np.asarray(q1, float))
    return np.asarray(p1, float) + p, _quat_mul(np.asarray(q1, float), np.asarray(q2, float))


def embodiment_spec(name: str) -> EmbodimentSpec:
    """The built-in embodiment called ``name``, or the one a robot file (``*.toml``, see
    ``docs/robots.md``) at the path ``name`` describes; raises listing the built-ins."""
    if name in EMBODIMENTS:
        return EMBODIMENTS[name]
    if is_robot_file(name) and Path(name).is_file():
        return load_robot_file(name)
    if is_robot_file(name):
        raise FileNotFoundError(
            f"robot file {name} does not exist (built-in embodiments: {', '.join(EMBODIMENTS)})"
        )
    check_name("embodiment", name, EMBODIMENTS, "(or a robot file: path/to/robot.toml)")
    raise AssertionError("unreachable")


def make_embodiment(name: str) -> Embodiment:
    """The embodiment ``name`` names (:func:`embodiment_spec`)."""
    return Embodiment(embodiment_spec(name))


def embodiment_layout(spec: EmbodimentSpec | str) -> str | None:
    """The built-in embodiment with the same effectors (names and sides) and no body, which
    tasks and traces written for it serve; ``None`` if there is none. A built-in is its own.
    ``spec``: an embodiment, or a name :func:`embodiment_spec` takes."""
    if isinstance(spec, str):
        spec = embodiment_spec(spec)
    if spec.name in EMBODIMENTS:
        return spec.name
    effectors = sorted((e.name, e.side) for e in spec.effectors)
    for name, builtin in EMBODIMENTS.items():
        if (
            builtin.body is None
            and sorted((e.name, e.side) for e in builtin.effectors) == effectors
        ):
            return name
    return None
