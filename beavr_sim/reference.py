"""Reference (third-party) models from ``../shared/reference``, for fidelity tests and benchmarks.

Only read here, never shipped: these build a scene with the Menagerie xArm7 and LEAP models
placed exactly like our embodiment (same bases, our documented hand mount), so that our model
and the reference can be compared joint for joint.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.robots import Embodiment

#: Menagerie LEAP body holding each of our fingertip-pad sites' distal links.
REFERENCE_DISTAL_BODY = {
    "thumb_distal": "thumb_fingertip",
    "index_distal": "fingertip",
    "middle_distal": "fingertip_2",
    "ring_distal": "fingertip_3",
}


def find_reference_dir() -> Path | None:
    """``$BEAVR_REFERENCE_DIR`` or ``../shared/reference`` beside the checkout, if present."""
    env = os.environ.get("BEAVR_REFERENCE_DIR")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared" / "reference")
    return next((c for c in candidates if c.is_dir()), None)


def reference_joint_name(name: str) -> str:
    """Our joint name -> the reference's (``right/leap_3`` -> ``right/3``)."""
    prefix, _, local = name.rpartition("/")
    return f"{prefix}/{local.removeprefix('leap_')}"


def _reference_hand(reference_dir: Path, side: str, keep_meshes: bool) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_file(str(reference_dir / "menagerie_leap_hand" / f"{side}_hand.xml"))
    # The reference palm meshes are missing (reference/README.md): drop those geoms at least.
    for geom in list(spec.geoms):
        if geom.type == mujoco.mjtGeom.mjGEOM_MESH and (
            not keep_meshes or geom.meshname.startswith("palm")
        ):
            spec.delete(geom)
    for mesh in list(spec.meshes):
        if not keep_meshes or mesh.name.startswith("palm"):
            spec.delete(mesh)
    for light in list(spec.lights):
        spec.delete(light)
    return spec


def _pose_in_site_frame(data: mujoco.MjData, site: str, body: str) -> tuple[np.ndarray, np.ndarray]:
    R_world_site = data.site(site).xmat.reshape(3, 3)
    R_world_body = data.body(body).xmat.reshape(3, 3)
    pos = R_world_site.T @ (data.body(body).xpos - data.site(site).xpos)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (R_world_site.T @ R_world_body).flatten())
    return pos, quat


def build_reference_model(
    embodiment: Embodiment, ours: mujoco.MjModel, reference_dir: Path, keep_meshes: bool = False
) -> mujoco.MjModel:
    """The reference arms and hands placed like ``embodiment`` in our compiled model ``ours``."""
    ours_data = mujoco.MjData(ours)
    mujoco.mj_kinematics(ours, ours_data)
    spec = mujoco.MjSpec()
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for eff_spec, eff in zip(embodiment.spec.effectors, embodiment.effectors, strict=True):
        arm = mujoco.MjSpec.from_file(
            str(reference_dir / "menagerie_ufactory_xarm7" / "xarm7_nohand.xml")
        )
        arm.delete(arm.key("home"))
        if not keep_meshes:
            for geom in list(arm.geoms):
                if geom.type == mujoco.mjtGeom.mjGEOM_MESH:
                    arm.delete(geom)
            for mesh in list(arm.meshes):
                arm.delete(mesh)
        # Our link_base frame is Menagerie's link_base frame; Menagerie lifts it 0.12 m.
        arm.body("link_base").pos = [0, 0, 0]
        base = spec.worldbody.add_frame(pos=list(eff_spec.base_pos))
        spec.attach(arm, prefix=eff_spec.prefix, frame=base)
        hand = _reference_hand(reference_dir, eff.side, keep_meshes)
        pos, quat = _pose_in_site_frame(ours_data, eff.ee_site, eff_spec.prefix + "palm")
        hand.body("palm_lower").pos = list(pos)
        hand.body("palm_lower").quat = list(quat)
        spec.attach(
            hand, prefix=eff_spec.prefix, site=spec.site(eff_spec.prefix + "attachment_site")
        )
    return spec.compile()


# --- the RX-1 (rx1_description/urdf/leap_rx1.urdf) -------------------------------------------

#: Our RX-1 joint (without its ``right/`` / ``left/`` / ``body/`` prefix) -> the URDF joint
#: (``{side}`` is the effector's side).
RX1_URDF_JOINTS = {
    "torso_yaw": "base2torso_yaw_joint",
    "torso_pitch": "torso_yaw2pitch_joint",
    "torso_roll": "torso_pitch2roll_joint",
    "neck_yaw": "head_base2neck_yaw_joint",
    "neck_pitch": "neck_yaw2pitch_joint",
    "head_roll": "neck_pitch2head_depth_cam_mount_joint",
    "shoulder_pitch": "{side}_shoul_base2shoul_joint",
    "shoulder_roll": "{side}_shoul2shoul_rot_joint",
    "arm_yaw": "{side}_arm2armrot_joint",
    "elbow": "{side}_armrot2elbow_joint",
    "forearm_yaw": "{side}_forearm2forearmrot_joint",
    "wrist_pitch": "{side}_forearmrot2forearm_pitch_joint",
    "wrist_roll": "{side}_forearm_pitch2forearm_roll_joint",
}
#: LEAP motor id -> URDF joint of the LEAP hand on the RX-1.
RX1_URDF_LEAP_JOINTS = {
    **{
        4 * f + k: f"{{side}}_{finger}_joint_{name}"
        for f, finger in enumerate(("index", "middle", "ring"))
        for k, name in enumerate(("mcp_to_pip", "palm_to_mcp", "pip_to_dip", "dip_to_fingertip"))
    },
    12: "{side}_thumb_joint_palm_to_base",
    13: "{side}_thumb_joint_base_to_pip",
    14: "{side}_thumb_joint_pip_to_dip",
    15: "{side}_thumb_joint_dip_to_fingertip",
}
#: Our hand body -> the URDF link of the same frame (``{side}`` is the effector's side).
RX1_URDF_LINK = {
    "thumb_distal": "urdf/{side}_thumb_fingertip",
    "index_distal": "urdf/{side}_index_fingertip",
    "middle_distal": "urdf/{side}_middle_fingertip",
    "ring_distal": "urdf/{side}_ring_fingertip",
    "palm": "urdf/{side}_palm_lower",
}


def rx1_urdf_joint_name(name: str) -> str:
    """Our RX-1 scene joint name -> the reference model's (``right/elbow`` ->
    ``urdf/right_armrot2elbow_joint``; see :func:`build_rx1_reference_model`)."""
    prefix, _, local = name.rpartition("/")
    if local.startswith("leap_"):
        return "urdf/" + RX1_URDF_LEAP_JOINTS[int(local.removeprefix("leap_"))].format(side=prefix)
    return "urdf/" + RX1_URDF_JOINTS[local].format(side=prefix)


def build_rx1_reference_model(reference_dir: Path, base_pos) -> mujoco.MjModel:
    """The RX-1 + LEAP URDF, loaded without meshes (it ships none), base at ``base_pos``.

    Every fixed link stays a body (``fusestatic`` off) so that URDF frames can be looked up;
    names carry the prefix ``urdf/``.
    """
    root = ET.parse(reference_dir / "rx1_description" / "urdf" / "leap_rx1.urdf").getroot()
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for element in link.findall(tag):
                link.remove(element)
    extension = ET.SubElement(root, "mujoco")
    # The URDF's inertias are placeholders (some break the triangle inequality): balance them.
    ET.SubElement(
        extension, "compiler", fusestatic="false", discardvisual="true", balanceinertia="true"
    )
    spec = mujoco.MjSpec.from_string(ET.tostring(root, encoding="unicode"))
    wrapper = mujoco.MjSpec()
    frame = wrapper.worldbody.add_frame(pos=list(base_pos))
    wrapper.attach(spec, prefix="urdf/", frame=frame)
    return wrapper.compile()
