"""Reference (third-party) models from ``../shared/reference``, for fidelity tests and benchmarks.

Only read here, never shipped: these build a scene with the Menagerie xArm7 and LEAP models
placed exactly like our embodiment (same bases, our documented hand mount), so that our model
and the reference can be compared joint for joint.
"""

from __future__ import annotations

import os
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
