"""Scene composition with ``mujoco.MjSpec``: floor, table, light, cameras, robots, task objects."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.envs.camera_pose import PlacedCamera, place_camera
from beavr_sim.naming import check_name
from beavr_sim.robots import EMBODIMENTS, Embodiment
from beavr_sim.workcell import TABLE_HALF_Y, TABLE_THICKNESS, TABLE_TOP_Z, TABLE_X

#: The scene's fixed cameras (every embodiment has them).
CAMERA_NAMES = ("front", "overhead")
#: Every camera name some embodiment has: the fixed ones, then those robots carry (the RX-1's
#: ``head``).
ALL_CAMERA_NAMES = CAMERA_NAMES + tuple(
    dict.fromkeys(c for spec in EMBODIMENTS.values() if spec.body for c in spec.body.cameras)
)


def camera_names(embodiment: Embodiment) -> tuple[str, ...]:
    """The cameras of ``embodiment``'s scene: the fixed ones, then the robot's own."""
    return CAMERA_NAMES + embodiment.cameras


#: The hands' hardware variant unless one is chosen (the LEAP hand: the full hand, not the Lite).
DEFAULT_HAND_VARIANT = "full"


def hand_variants(embodiment: Embodiment) -> tuple[str, ...]:
    """The hardware variants every hand of ``embodiment`` comes in (LEAP: full, lite); just
    the default where no hand has variants."""
    hands = [e.hand for e in embodiment.spec.effectors if e.hand.variants]
    if not hands:
        return (DEFAULT_HAND_VARIANT,)
    return tuple(v for v in hands[0].variants if all(v in h.variants for h in hands))


def check_hand_variant(embodiment: Embodiment, variant: str) -> str:
    """``variant`` if every hand of ``embodiment`` comes in it, else an error listing those."""
    return check_name(
        "hand variant", variant, hand_variants(embodiment), f"for embodiment {embodiment.name}"
    )


def apply_hand_variant(spec: mujoco.MjSpec, embodiment: Embodiment, variant: str) -> None:
    """Cap every finger joint of ``embodiment``'s hands at the torque cap of ``variant``
    (``HandModel.torque_cap``): its actuator's force range and the joint's actuator force
    range. Hands without variants keep their file's limits."""
    check_hand_variant(embodiment, variant)
    for effector in embodiment.spec.effectors:
        hand = effector.hand
        if not hand.variants:
            continue
        cap = hand.torque_cap(variant)
        joints = {effector.prefix + j for j in hand.joints}
        capped = set()
        for actuator in spec.actuators:
            if actuator.target in joints:
                actuator.forcerange = [-cap, cap]
                capped.add(actuator.target)
        if capped != joints:
            raise ValueError(
                f"{effector.name}: no actuator on hand joints {sorted(joints - capped)}"
            )
        for name in joints:
            spec.joint(name).actfrcrange = [-cap, cap]


#: MuJoCo friction cones by name.
CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}


@dataclass(frozen=True)
class ContactSettings:
    """The scene's global contact options: the friction cone and ``impratio`` (the ratio of
    frictional to normal constraint impedance; > 1 resists slip more). The default was chosen
    by measurement (``python -m beavr_sim.bench contact``; docs/models.md, "Contact settings")."""

    cone: str = "pyramidal"
    impratio: float = 1.0

    def __post_init__(self) -> None:
        check_name("cone", self.cone, tuple(CONES))
        if not (np.isfinite(self.impratio) and self.impratio >= 1.0):
            raise ValueError(f"impratio must be a finite number >= 1, got {self.impratio!r}")

    def apply(self, spec: mujoco.MjSpec) -> None:
        spec.option.cone = CONES[self.cone]
        spec.option.impratio = float(self.impratio)


DEFAULT_CONTACT = ContactSettings()


@dataclass(frozen=True)
class CameraConfig:
    """A fixed camera: position and a point it looks at (world frame), vertical field of view."""

    pos: tuple[float, float, float]
    target: tuple[float, float, float]
    fovy_deg: float


CAMERAS = {
    # Facing the robot from the far side of the table, as the paper's front camera.
    "front": CameraConfig(
        pos=(1.45, 0.0, 1.35), target=(0.35, 0.0, TABLE_TOP_Z + 0.1), fovy_deg=55.0
    ),
    # Straight down on the workspace.
    "overhead": CameraConfig(pos=(0.4, 0.0, 2.05), target=(0.4, 0.0, TABLE_TOP_Z), fovy_deg=60.0),
}


def _look_at_quat(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera quaternion looking from ``pos`` to ``target`` with world +z up in the image."""
    forward = target - pos
    forward /= np.linalg.norm(forward)
    up_world = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x_cam = np.cross(forward, up_world)
    x_cam /= np.linalg.norm(x_cam)
    y_cam = np.cross(-forward, x_cam)
    R_world_cam = np.column_stack([x_cam, y_cam, -forward])  # MuJoCo cameras look along -z
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, R_world_cam.flatten())
    return quat


def build_scene_spec(
    embodiment: Embodiment,
    height: int,
    width: int,
    hand_variant: str = DEFAULT_HAND_VARIANT,
    contact: ContactSettings = DEFAULT_CONTACT,
    visuals: bool = False,
    placed_cameras: Sequence[PlacedCamera] = (),
) -> mujoco.MjSpec:
    """The scene without task objects: everything every task shares. The hands are the
    ``hand_variant`` of their hardware (their torque cap: :func:`apply_hand_variant`);
    ``contact``: the global contact options; ``visuals``: the robots' visual geometry too
    (what the env and its views draw; the physics is the same without it, and the
    operator's and guards' private models leave it out); ``placed_cameras``: cameras at real
    cameras' poses (:mod:`beavr_sim.envs.camera_pose`), moving a fixed camera of the same name
    or added to the fixed ones."""
    check_hand_variant(embodiment, hand_variant)
    spec = mujoco.MjSpec()
    spec.modelname = f"beavr_sim_{embodiment.name}"
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    contact.apply(spec)
    spec.visual.global_.offwidth = max(width, 640)
    spec.visual.global_.offheight = max(height, 480)
    spec.visual.quality.shadowsize = 2048

    world = spec.worldbody
    spec.add_texture(
        name="grid",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.32, 0.34, 0.36],
        rgb2=[0.27, 0.29, 0.31],
        width=256,
        height=256,
    )
    spec.add_material(name="floor", textures=["", "grid"], texrepeat=[4, 4], reflectance=0.0)
    spec.add_material(name="table", rgba=[0.62, 0.5, 0.38, 1.0])
    world.add_light(
        name="key",
        pos=[0.6, -0.6, 2.6],
        dir=[-0.2, 0.25, -1.0],
        diffuse=[0.7, 0.7, 0.7],
        castshadow=False,
    )
    world.add_light(
        name="fill",
        pos=[0.0, 0.8, 2.4],
        dir=[0.2, -0.4, -1.0],
        diffuse=[0.35, 0.35, 0.35],
        castshadow=False,
    )
    world.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.05], material="floor"
    )

    table = world.add_body(name="table", pos=[(TABLE_X[0] + TABLE_X[1]) / 2, 0.0, TABLE_TOP_Z])
    half_x = (TABLE_X[1] - TABLE_X[0]) / 2
    table.add_geom(
        name="table_top",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        material="table",
        size=[half_x, TABLE_HALF_Y, TABLE_THICKNESS / 2],
        pos=[0, 0, -TABLE_THICKNESS / 2],
    )
    leg_h = (TABLE_TOP_Z - TABLE_THICKNESS) / 2
    for sx in (-1, 1):
        for sy in (-1, 1):
            table.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX,
                material="table",
                contype=0,
                conaffinity=0,
                size=[0.03, 0.03, leg_h],
                pos=[sx * (half_x - 0.05), sy * (TABLE_HALF_Y - 0.05), -TABLE_THICKNESS - leg_h],
            )

    shift = np.asarray(embodiment.spec.camera_shift, dtype=float)
    for name in CAMERA_NAMES:
        cam = CAMERAS[name]
        pos, target = np.array(cam.pos) + shift, np.array(cam.target) + shift
        world.add_camera(
            name=name, pos=list(pos), fovy=cam.fovy_deg, quat=list(_look_at_quat(pos, target))
        )

    if embodiment.spec.body is not None and embodiment.spec.body_pos[2] > 0:
        # A stand under a body that does not reach the floor.
        x, y, z = embodiment.spec.body_pos
        world.add_geom(
            name="robot_stand",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            material="table",
            size=[0.17, 0.17, z / 2],
            pos=[x, y, z / 2],
        )
    embodiment.attach_to(spec, visuals=visuals)
    for placed in placed_cameras:
        place_camera(spec, placed)
    apply_hand_variant(spec, embodiment, hand_variant)
    if embodiment.spec.body is None:
        for effector in embodiment.spec.effectors:
            # The base bolts onto the table; their primitives overlap by construction.
            spec.add_exclude(bodyname1="table", bodyname2=effector.prefix + effector.arm.root_body)
    return spec
