"""A robot file -> an :class:`~beavr_sim.robots.embodiment.EmbodimentSpec`, deriving the rest.

Each arm's model (MJCF, URDF, or an MJCF fragment with its fragments) is loaded with MuJoCo's
compiler and written back as one *arm part*: an MJCF file in the user's cache
(``$XDG_CACHE_HOME/beavr_sim/robots/``, keyed by the robot file's and models' contents) that
the embodiment attaches like a bundled part. Writing it:

- keeps only the base body's subtree, minus ``remove_bodies`` and the geoms of
  ``remove_meshes`` (a stock gripper); every joint left must be one of ``joints``;
- freezes each body's mass and inertia as compiled, so visual geoms can be dropped from the
  physics without changing it;
- adds a ``flange`` site (the hand's mount, +z out of the flange) and one position servo per
  joint (``servo`` gains, critically damped by default; ctrl range = joint range), whose
  damping replaces the model's passive joint damping;
- keeps the model's contact excludes between links that stay (a base welded to the world and
  its first link may touch by design), dropping those that name a removed body;
- reads the joint limits from the model (``limits_deg`` only where the model has none);
- turns gravity compensation on (arm controllers compensate gravity);
- moves visual geoms (contype = conaffinity = 0) to the visual group and collision geoms to
  the collision group (:mod:`beavr_sim.robots.visuals`), and makes mesh paths absolute.

The upper-arm and forearm links the operator's IK keeps clear default to the links before and
after the middle joint. Anything else the operator, the guard and the twin need they derive
from the compiled scene, as for the built-in robots.

An effector's ``hand`` is the LEAP hand, or a ``[hands.NAME]`` table of the file: a hand from
its own MJCF (:mod:`beavr_sim.robots.hand_file`), written as a *hand part* beside the arm
parts. Its top body ``hand`` is the hand's mount frame in the LEAP hand's convention (the
human palm frame's: +z along the fingers, +x out of the palm, thumb at +y on a right hand),
the model's root (palm) body at its origin turned by ``palm_axes``; below it the root's
subtree, without the joints on the root itself (a wrist: the arm's job). Writing it drops the
model's actuators, tendons (so tendon-coupled joints move independently), sensors,
equalities, keyframes, contact pairs and excludes (its geoms keep their own contact bits);
freezes inertia;
adds one position servo per hand joint (the table's ``servo``; ctrl range = joint range),
whose damping replaces the model's passive joint damping; adds a ``palm_centre`` site (unless
the hand has one) and a ``tip_<finger>`` site per finger; sorts geoms into the visual and collision groups as above.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.robots.hand_file import ModelHand, load_hand, tip_points
from beavr_sim.robots.parts import LEAP_HAND, ArmModel, ArmServo, HandModel, HandMount
from beavr_sim.robots.robot_file import (
    ArmFile,
    HandFile,
    RobotFile,
    RobotFileError,
    read_robot_file,
)
from beavr_sim.robots.specs import EffectorSpec, EmbodimentSpec
from beavr_sim.robots.visuals import COLLISION_GROUP, VISUAL_GROUP
from beavr_sim.workcell import TABLE_TOP_Z

#: Name of the site the hand mounts on, in every written arm part.
FLANGE_SITE = "flange"
HANDS = {"leap": LEAP_HAND}
#: The top body of every written hand part: the hand's mount frame (as the LEAP hand's).
HAND_BODY = "hand"
#: The palm site of every written hand part.
PALM_SITE = "palm_centre"
#: A prefix the hand part's names carry while it is built (none in the written file).
_PART_PREFIX = "beavr-hand-part-prefix:"


def cache_dir() -> Path:
    """Where written arm parts live: ``$XDG_CACHE_HOME/beavr_sim/robots``."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "beavr_sim" / "robots"


def load_robot_file(path: str | Path) -> EmbodimentSpec:
    """The embodiment a robot file describes. Its name is the file's absolute path, so every
    process of a pipeline (which pass embodiments by name) loads the same robot."""
    robot = read_robot_file(path)
    arms = {name: arm_model(robot, arm) for name, arm in robot.arms.items()}
    hands = dict(HANDS)
    for name, hand in robot.hands.items():
        if any(e.hand == name for e in robot.effectors):
            hands[name] = hand_model(robot, hand)
    effectors = tuple(
        EffectorSpec(
            name=e.name,
            side=e.side,
            base_pos=(e.base_pos[0], e.base_pos[1], e.base_pos[2] + TABLE_TOP_Z),
            base_yaw_deg=e.base_yaw_deg,
            arm=arms[e.arm],
            hand=hands[e.hand],
            mount=HandMount(pos=e.mount.pos, yaw_deg_by_side={e.side: e.mount.yaw_deg}),
        )
        for e in robot.effectors
    )
    description = robot.description or f"{robot.name} (from {robot.path.name})"
    return EmbodimentSpec(
        str(robot.path),
        effectors,
        description,
        workspace=robot.workspace,
        guard_box=(
            None
            if robot.guard_box is None
            else tuple((x, y, z + TABLE_TOP_Z) for x, y, z in robot.guard_box)  # type: ignore[misc]
        ),
    )


def arm_model(robot: RobotFile, arm: ArmFile) -> ArmModel:
    """The :class:`ArmModel` of ``arm``, its part written to the cache if not there yet."""
    sides = sorted({e.side for e in robot.effectors if e.arm == arm.name})
    spec = load_arm_spec(robot, arm)
    upper, forearm = arm_links(spec, arm)
    part = cache_dir() / f"{robot.name}-{_digest(robot, arm)}" / f"{arm.name}.xml"
    if not part.is_file():
        write_arm_part(spec, robot, arm, part)
    _check_home(mujoco.MjModel.from_xml_path(str(part)), robot, arm, sides)
    return ArmModel(
        name=arm.name,
        mjcf=str(part),
        joints=arm.joints,
        home_by_side={s: tuple(math.radians(v) for v in arm.home(s)) for s in sides},
        ee_site=FLANGE_SITE,
        root_body=arm.base_body,
        upper_arm_links=upper,
        forearm_links=forearm,
        servo=ArmServo(
            max_velocity=math.radians(arm.max_velocity_deg_s),
            max_acceleration=arm.max_acceleration_rad_s2,
        ),
    )


def load_arm_spec(robot: RobotFile, arm: ArmFile) -> mujoco.MjSpec:
    """The arm's model as MuJoCo reads it, its mesh paths absolute, names checked."""
    where = f"{robot.path}: arms.{arm.name}"
    try:
        if _is_fragment(arm.model):
            body = "".join(f'<include file="{f}"/>' for f in arm.fragments)
            xml = (
                f'<mujoco model="{arm.name}">{body}'
                f'<worldbody><include file="{arm.model}"/></worldbody></mujoco>'
            )
            spec = mujoco.MjSpec.from_string(xml)
        else:
            if arm.fragments:
                raise RobotFileError(f"{where}.fragments: only a <mujocoinclude> model has them")
            spec = mujoco.MjSpec.from_file(str(arm.model))
    except ValueError as e:
        if isinstance(e, RobotFileError):
            raise
        raise RobotFileError(f"{where}.model: MuJoCo cannot read {arm.model}: {e}") from e
    _absolute_meshes(spec, arm.model, arm.fragments, arm.asset_root, where)
    bodies = [b.name for b in spec.bodies if b.name and b.name != spec.worldbody.name]
    for key, name in (("base_body", arm.base_body), ("flange.body", arm.flange.body)):
        if name and spec.body(name) is None:
            raise RobotFileError(f"{where}.{key}: no body {name!r}; bodies: {', '.join(bodies)}")
    if arm.flange.site and spec.site(arm.flange.site) is None:
        sites = ", ".join(s.name for s in spec.sites if s.name) or "none"
        raise RobotFileError(f"{where}.flange.site: no site {arm.flange.site!r}; sites: {sites}")
    for name in arm.remove_bodies:
        if spec.body(name) is None:
            raise RobotFileError(
                f"{where}.remove_bodies: no body {name!r}; bodies: {', '.join(bodies)}"
            )
    meshes = {m.name for m in spec.meshes}
    for name in arm.remove_meshes:
        if name not in meshes:
            raise RobotFileError(
                f"{where}.remove_meshes: no mesh {name!r}; meshes: {', '.join(sorted(meshes))}"
            )
    _strip(spec, arm)
    joints = [j.name for j in spec.joints]
    for name in arm.joints:
        if name not in joints:
            raise RobotFileError(f"{where}.joints: no joint {name!r}; joints: {', '.join(joints)}")
    extra = [j for j in joints if j not in arm.joints]
    if extra:
        raise RobotFileError(
            f"{where}.joints: the model also has joints {extra} under {arm.base_body!r}: list "
            "them in joints, or name their bodies in remove_bodies"
        )
    for name in arm.joints:
        joint = spec.joint(name)
        if joint.type not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            raise RobotFileError(f"{where}.joints: {name!r} is not a hinge or slide joint")
    return spec


def arm_links(spec: mujoco.MjSpec, arm: ArmFile) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The upper-arm and forearm links: the file's, else the base and the links before the
    middle joint, and the links after it."""
    bodies = [spec.joint(j).parent.name for j in arm.joints]
    middle = (len(bodies) + 1) // 2  # 1-based index of the middle (elbow) joint
    upper = arm.upper_arm_links
    if upper is None:
        upper = tuple(dict.fromkeys((arm.base_body, *bodies[: middle - 1])))
    forearm = arm.forearm_links
    if forearm is None:
        forearm = tuple(b for b in dict.fromkeys(bodies[middle:]) if b not in upper)
    for name in (*upper, *forearm):
        if spec.body(name) is None:
            raise RobotFileError(f"arms.{arm.name}: no link {name!r} (upper/forearm links)")
    return tuple(upper), tuple(forearm)


def _freeze_inertia(body, model: mujoco.MjModel) -> None:
    """Give the spec ``body`` the mass and inertia it compiled to in ``model`` (explicit), so
    geoms can leave the physics without changing it."""
    compiled = model.body(body.name)
    body.explicitinertial = True
    body.mass = float(compiled.mass[0])
    body.ipos = compiled.ipos.tolist()
    body.iquat = compiled.iquat.tolist()
    body.inertia = compiled.inertia.tolist()
    body.fullinertia = [math.nan] * 6


def _sort_geoms(spec: mujoco.MjSpec) -> None:
    """Collision geoms (any contact bit) to the collision group; visual ones to the visual
    group, massless (the bodies' inertia is frozen first)."""
    for geom in spec.geoms:
        if geom.contype or geom.conaffinity:
            geom.group = COLLISION_GROUP
        else:
            geom.group = VISUAL_GROUP
            geom.mass = 0.0
            geom.density = 0.0


def write_arm_part(spec: mujoco.MjSpec, robot: RobotFile, arm: ArmFile, path: Path) -> None:
    """Write ``arm``'s part (see the module docstring) to ``path`` atomically."""
    where = f"{robot.path}: arms.{arm.name}"
    model = spec.compile()
    for body in spec.bodies:
        if body.name and body is not spec.worldbody:
            _freeze_inertia(body, model)
            moving = body.name != arm.base_body
            body.gravcomp = 1.0 if arm.gravity_compensation and moving else 0.0
    _sort_geoms(spec)
    if arm.flange.site:
        site = spec.site(arm.flange.site)
        site.name = FLANGE_SITE
    else:
        spec.body(arm.flange.body).add_site(name=FLANGE_SITE, pos=list(arm.flange.pos))
    for actuator in list(spec.actuators):
        spec.delete(actuator)
    spec.nuser_actuator = -1
    kv = arm.servo.damping
    for name in arm.joints:
        joint = spec.joint(name)
        index = model.joint(name).id
        limited = bool(model.jnt_limited[index])
        if name in arm.limits_deg:
            if limited:
                raise RobotFileError(
                    f"{where}.limits_deg.{name}: the model limits this joint already "
                    f"({np.degrees(model.jnt_range[index]).round(1).tolist()} deg)"
                )
            joint.range = [math.radians(v) for v in arm.limits_deg[name]]
            joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        elif not limited:
            raise RobotFileError(
                f"{where}.joints: {name!r} has no limits in the model; give them as "
                f"limits_deg.{name} = [lower, upper]"
            )
        # The servo's kv is the joint's damping: a model's own passive damping (tuned for its
        # own actuators) would add to it and, under the torque cap, cap the joint's speed at
        # force_limit / damping (the Panda's 100 N m s/rad: 50 deg/s against 87 N m).
        joint.damping = np.zeros_like(joint.damping)
        actuator = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        actuator.set_to_position(kp=arm.servo.kp, kv=kv)
        actuator.ctrlrange = list(joint.range)
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        force = arm.servo.force_limit or (
            float(model.jnt_actfrcrange[index, 1]) if model.jnt_actfrclimited[index] else 0.0
        )
        if force > 0:
            actuator.forcerange = [-force, force]
            actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    spec.modelname = f"{robot.name}_{arm.name}"
    try:
        spec.compile()
    except ValueError as e:
        raise RobotFileError(f"{where}: the arm part does not compile: {e}") from e
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False) as f:
        f.write(spec.to_xml())
    os.replace(f.name, path)


def hand_model(robot: RobotFile, hand_file: HandFile) -> HandModel:
    """The :class:`HandModel` of a ``[hands.NAME]`` table, its part written to the cache if
    not there yet (see the module docstring). One part serves every side naming it."""
    hand = load_hand(hand_file, robot.path)
    sides = sorted({e.side for e in robot.effectors if e.hand == hand_file.name})
    part = (
        cache_dir()
        / f"{robot.name}-{_hand_digest(robot, hand_file)}"
        / f"hand_{hand.spec.name}.xml"
    )
    if not part.is_file():
        write_hand_part(robot, hand, part)
    tip_bodies = []
    for _, kind, i in hand.tips:
        body = int(hand.model.site_bodyid[i]) if kind == "site" else i
        tip_bodies.append(hand.model.body(body).name)
    return HandModel(
        name=hand_file.name,
        mjcf_by_side={side: str(part) for side in sides},
        joints=hand.joint_names,
        palm_site=PALM_SITE,
        fingertip_sites=tuple(f"tip_{f}" for f, _, _ in hand.tips),
        root_body=HAND_BODY,
        home=tuple(float(v) for v in hand.home),
        palm_body=hand_file.root,
        collision_bodies=tuple(dict.fromkeys((hand_file.root, *tip_bodies))),
        max_velocity=math.radians(hand_file.max_velocity_deg_s),
        source=hand_file,
    )


def write_hand_part(robot: RobotFile, hand: ModelHand, path: Path) -> None:
    """Write the hand part of ``hand`` (see the module docstring) to ``path`` atomically."""
    spec_file = hand.spec
    where = f"{robot.path}: hands.{spec_file.name}"
    src = mujoco.MjSpec.from_file(str(spec_file.model))
    _absolute_meshes(src, spec_file.model, (), None, where)
    # The model's contact pairs go too: the operator's distance model takes only its own
    # pairs (and MuJoCo cannot delete pairs from a spec with attached parts).
    for kind in ("sensors", "tendons", "actuators", "equalities", "keys", "pairs", "excludes"):
        for item in list(getattr(src, kind)):
            src.delete(item)
    compiled = src.compile()
    root = src.body(spec_file.root)
    subtree = _subtree_names(root)
    for body in src.bodies:
        if body.name in subtree:
            _freeze_inertia(body, compiled)
            body.gravcomp = 0.0
    for joint in list(root.joints):  # a wrist on the root: the arm moves the hand
        src.delete(joint)
    joints = [j.name for j in src.joints if j.parent.name in subtree]
    extra = [j for j in joints if j not in hand.joint_names]
    if extra:
        raise RobotFileError(
            f"{where}.joints: the model also has joints {extra} below {spec_file.root!r}: "
            "list them in joints (the twin needs a servo on every joint of the hand)"
        )
    for (finger, kind, i), name in zip(hand.tips, (f"tip_{f}" for f, _, _ in hand.tips),
                                       strict=True):  # fmt: skip
        if kind == "site":
            site = src.site(hand.model.site(i).name)
            owner, pos = site.parent, list(site.pos)
        else:
            owner, pos = src.body(hand.model.body(i).name), [0.0] * 3
        if src.site(name) is not None:
            raise RobotFileError(f"{where}.fingers.{finger}: the model has a site {name!r} already")
        owner.add_site(name=name, pos=pos, group=4)
    data = mujoco.MjData(hand.model)
    data.qpos[hand.qpos_ids] = hand.home
    mujoco.mj_kinematics(hand.model, data)
    centre = 0.5 * tip_points(hand, data).mean(axis=0)  # halfway to the tips: the palm's middle
    own = src.site(PALM_SITE)
    if own is None:
        root.add_site(name=PALM_SITE, pos=centre.tolist(), group=4)
    elif own.parent.name not in subtree:
        raise RobotFileError(f"{where}: the model has a site {PALM_SITE!r} outside the hand")
    _sort_geoms(src)

    out = mujoco.MjSpec()
    out.modelname = f"{robot.name}_{spec_file.name}"
    out.compiler.degree = src.compiler.degree
    top = out.worldbody.add_body(name=HAND_BODY)
    fresh = mujoco.MjSpec()  # the source's sizes and solver options: the scene's win
    for key in ("njmax", "nconmax", "nstack", *(f"nuser_{k}" for k in
                ("jnt", "site", "geom", "body", "tendon", "actuator", "sensor"))):  # fmt: skip
        setattr(src, key, getattr(fresh, key))
    src.option.iterations = fresh.option.iterations
    root.pos = [0.0, 0.0, 0.0]  # the root's frame is placed by the hand frame alone
    root.quat = [1.0, 0.0, 0.0, 0.0]
    root.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(hand.R_palm_root.T).reshape(9))
    frame = top.add_frame(quat=quat.tolist())
    # Attached under a prefix (MuJoCo warns of an empty one), removed from the written text.
    frame.attach_body(root, _PART_PREFIX, "")
    used = {g.meshname for g in out.geoms if g.meshname}
    for mesh in list(out.meshes):
        if mesh.name not in used:
            out.delete(mesh)
    for actuator in list(out.actuators):
        out.delete(actuator)
    for kind in ("bodies", "joints", "geoms", "sites"):  # the model's user data: none of ours
        for item in getattr(out, kind):
            item.userdata = []
    for kind in ("jnt", "site", "geom", "body", "tendon", "actuator", "sensor"):
        setattr(out, f"nuser_{kind}", -1)
    servo = spec_file.servo
    model = out.compile()
    for name in (_PART_PREFIX + j for j in hand.joint_names):
        joint = out.joint(name)
        index = model.joint(name).id
        joint.damping = np.zeros_like(joint.damping)
        actuator = out.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        actuator.set_to_position(kp=servo.kp, kv=servo.damping)
        actuator.ctrlrange = list(model.jnt_range[index])
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        force = servo.force_limit or (
            float(model.jnt_actfrcrange[index, 1]) if model.jnt_actfrclimited[index] else 0.0
        )
        if force > 0:
            actuator.forcerange = [-force, force]
            actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    xml = out.to_xml()  # the source's top default class would repeat the part's own "main"
    xml = xml.replace(f'"{_PART_PREFIX}main"', '"hand_main"').replace(_PART_PREFIX, "")
    try:
        mujoco.MjModel.from_xml_string(xml)
    except ValueError as e:
        raise RobotFileError(f"{where}: the hand part does not compile: {e}") from e
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False) as f:
        f.write(xml)
    os.replace(f.name, path)


def _subtree_names(body) -> set[str]:
    names = {body.name}
    for child in body.bodies:
        names |= _subtree_names(child)
    return names


def _check_home(part: mujoco.MjModel, robot: RobotFile, arm: ArmFile, sides) -> None:
    """Raise naming the joint, its limits and the key when a home pose leaves the limits."""
    for side in sides:
        key = "home_deg_by_side." + side if side in arm.home_deg_by_side else "home_deg"
        for name, value in zip(arm.joints, arm.home(side), strict=True):
            lo, hi = np.degrees(part.joint(name).range)
            if not lo <= value <= hi:
                raise RobotFileError(
                    f"{robot.path}: arms.{arm.name}.{key}: {name} = {value} deg is outside its "
                    f"limits [{lo:.1f}, {hi:.1f}] deg"
                )


def _is_fragment(path: Path) -> bool:
    with path.open("rb") as f:
        return b"<mujocoinclude" in f.read(4096)


def _absolute_meshes(
    spec: mujoco.MjSpec, model: Path, fragments, asset_root: Path | None, where: str
) -> None:
    """Point every mesh at its file by an absolute path. A relative ``meshdir`` is relative
    to ``asset_root`` (default: the model's folder); MuJoCo reads a fragment's mesh paths
    relative to the fragment's folder, which ``asset_root`` corrects."""
    root = asset_root or model.parent
    meshdir = root / spec.meshdir if spec.meshdir else root
    sources = [p.parent for p in (model, *fragments)]
    for mesh in spec.meshes:
        if not mesh.file:
            continue
        file = Path(mesh.file)
        candidates = [file] if file.is_absolute() else [meshdir / file, root / file]
        candidates += [meshdir / file.relative_to(s) for s in sources if file.is_relative_to(s)]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise RobotFileError(
                f"{where}: mesh {mesh.name!r}: no file at {', '.join(map(str, candidates))}; "
                "set asset_root to the folder the model's meshdir is relative to"
            )
        mesh.file = str(found.resolve())
    spec.meshdir = ""


def _strip(spec: mujoco.MjSpec, arm: ArmFile) -> None:
    """Keep the base body's subtree minus the removed bodies and meshes' geoms."""
    base = spec.body(arm.base_body)
    for body in list(spec.worldbody.bodies):
        if body.name != base.name and not _contains(body, base):
            spec.delete(body)
    if base.parent.name != spec.worldbody.name:
        raise RobotFileError(
            f"arms.{arm.name}.base_body: {arm.base_body!r} is not a top-level body of the "
            f"model (its parent is {base.parent.name!r}): name the model's root link"
        )
    for name in arm.remove_bodies:
        spec.delete(spec.body(name))
    removed = set(arm.remove_meshes)
    for geom in list(spec.geoms):
        if geom.meshname in removed:
            spec.delete(geom)
    for mesh in list(spec.meshes):
        if mesh.name in removed:
            spec.delete(mesh)
    for geom in list(spec.worldbody.geoms):
        spec.delete(geom)
    for kind in ("sensors", "tendons", "equalities", "keys"):
        for item in list(getattr(spec, kind)):
            spec.delete(item)
    # Contact excludes between links that stay are the model's own statement of which links
    # touch by design (a base welded to the world and its first link, which the parent-child
    # filter does not cover); those naming a removed body go.
    kept = {body.name for body in spec.bodies}
    for exclude in list(spec.excludes):
        if exclude.bodyname1 not in kept or exclude.bodyname2 not in kept:
            spec.delete(exclude)


def _contains(body, target) -> bool:
    return any(child.name == target.name or _contains(child, target) for child in body.bodies)


def _hand_digest(robot: RobotFile, hand: HandFile) -> str:
    """The hand part's cache key: this writer, the robot file, the model and its includes
    (every file of the model's folder that it names)."""
    h = hashlib.sha256(f"{mujoco.__version__}\n".encode())
    h.update(Path(__file__).read_bytes())
    h.update(robot.path.read_bytes())
    h.update(str(hand.model).encode())
    for path in sorted(hand.model.parent.glob("*.xml")):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def _digest(robot: RobotFile, arm: ArmFile) -> str:
    h = hashlib.sha256(f"{mujoco.__version__}\n".encode())
    h.update(Path(__file__).read_bytes())  # this writer's own code
    h.update(robot.path.read_bytes())
    for path in (arm.model, *arm.fragments):
        h.update(str(path).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:12]
