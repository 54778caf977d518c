"""``robots check``: load a robot file, compose its scene, run gymnasium's ``check_env`` and
report what was derived and what is missing.

:func:`check_robot` returns a :class:`RobotReport`: the derived facts per effector (joint
limits read from the model, reach, the IK's collision pairs, geoms touching at home, the hand's
finger scales) and ``missing``: what keeps the robot from a use, each with what to do. It
raises (a one-line :class:`~beavr_sim.robots.robot_file.RobotFileError` naming the key) when
the file cannot be loaded at all.
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.utils.env_checker import check_env

from beavr_sim.assets import bundled_traces
from beavr_sim.operator.arm_ik import ArmIK, ArmIKConfig
from beavr_sim.operator.retarget import HandMap, RetargetConfig
from beavr_sim.operator.retarget_model import finger_scales
from beavr_sim.robots.embodiment import Embodiment, embodiment_layout, embodiment_spec
from beavr_sim.robots.hand_file import load_hand
from beavr_sim.tasks.registry import TASKS, task_class


@dataclass(frozen=True)
class EffectorFacts:
    """What was derived for one effector."""

    name: str
    side: str
    part: str
    joints: tuple[str, ...]
    limits_deg: tuple[tuple[float, float], ...]
    home_deg: tuple[float, ...]
    max_velocity_deg_s: float
    reach_m: float
    flange_home_world: tuple[float, float, float]
    ik_link_pairs: int
    ik_wall_pairs: int
    touching_at_home: tuple[str, ...]
    hand: str
    hand_joints: int
    finger_scales: dict[str, float]
    upper_arm_links: tuple[str, ...]
    forearm_links: tuple[str, ...]


@dataclass(frozen=True)
class RobotReport:
    """The result of checking a robot file."""

    path: str
    description: str
    layout: str | None
    tasks: tuple[str, ...]
    task_checked: str | None
    check_env: str
    effectors: tuple[EffectorFacts, ...]
    missing: tuple[str, ...] = field(default=())

    @property
    def ok(self) -> bool:
        return self.check_env == "passed" and not self.missing


def check_robot(path: str | Path, task: str | None = None) -> RobotReport:
    """Check the robot file at ``path`` (see the module docstring); ``task``: the task whose
    env ``check_env`` runs on (default: the first task the robot's layout runs)."""
    spec = embodiment_spec(str(Path(path).resolve()))
    embodiment = Embodiment(spec)
    layout = embodiment_layout(spec)
    tasks = tuple(
        name
        for name in TASKS
        if layout is not None
        and (task_class(name).embodiments is None or layout in task_class(name).embodiments)
    )
    missing = []
    if layout is None:
        missing.append(
            "layout: no built-in embodiment has these effectors (names and sides), so no task, "
            "bundled trace or arm axis map serves it; name the effectors 'right' (side right), "
            "'left' (side left), or 'left' and 'right'"
        )
    elif not bundled_traces().get(layout):
        missing.append(f"traces: no bundled trace for layout {layout}")
    chosen = task if task is not None else (tasks[0] if tasks else None)
    result = "not run (no task)"
    if chosen is not None:
        env = gym.make(f"beavr_sim/{chosen}-v0", embodiment=spec.name)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # check_env's advice on Box bounds
                check_env(env.unwrapped, skip_render_check=True)
            result = "passed"
        except Exception as e:
            result = f"failed: {type(e).__name__}: {e}"
            missing.append(f"check_env on {chosen}: {e}")
        finally:
            env.close()
    facts = tuple(_effector_facts(embodiment, i) for i in range(len(spec.effectors)))
    return RobotReport(
        path=spec.name,
        description=spec.description,
        layout=layout,
        tasks=tasks,
        task_checked=chosen,
        check_env=result,
        effectors=facts,
        missing=tuple(missing),
    )


def _effector_facts(embodiment: Embodiment, index: int) -> EffectorFacts:
    e_spec = embodiment.spec.effectors[index]
    effector = embodiment.effectors[index]
    ik = ArmIK(embodiment, effector.name, 1 / 30, ArmIKConfig())
    model = ik.model
    data = mujoco.MjData(model)
    data.qpos[ik.joints.qpos_adr] = ik.joints.home
    mujoco.mj_kinematics(model, data)
    n_arm = len(e_spec.arm.joints)
    arm_ids = [model.joint(j).id for j in effector.arm_joints]
    anchors = [data.xanchor[j] for j in arm_ids] + [data.site(effector.ee_site).xpos]
    reach = float(sum(np.linalg.norm(b - a) for a, b in itertools.pairwise(anchors)))
    touching = []
    mujoco.mj_forward(model, data)
    for c in data.contact[: data.ncon]:
        if c.dist < 0:
            a, b = (model.body(model.geom_bodyid[g]).name for g in (c.geom1, c.geom2))
            touching.append(f"{a} / {b} ({-c.dist * 1000:.1f} mm)")
    if e_spec.hand.source is None:
        scales = HandMap(e_spec.side, RetargetConfig()).scales
    else:
        scales = finger_scales(load_hand(e_spec.hand.source), e_spec.side)
    lower = ik.joints.lower[:n_arm]
    upper = ik.joints.upper[:n_arm]
    return EffectorFacts(
        name=effector.name,
        side=effector.side,
        part=e_spec.arm.mjcf_for(e_spec.side),
        joints=e_spec.arm.joints,
        limits_deg=tuple(
            (round(math.degrees(lo), 1), round(math.degrees(hi), 1))
            for lo, hi in zip(lower, upper, strict=True)
        ),
        home_deg=tuple(round(math.degrees(q), 1) for q in e_spec.arm.home(e_spec.side)),
        max_velocity_deg_s=(
            round(math.degrees(e_spec.arm.servo.max_velocity), 1) if e_spec.arm.servo else math.nan
        ),
        reach_m=round(reach, 3),
        flange_home_world=tuple(round(float(v), 3) for v in data.site(effector.ee_site).xpos),  # type: ignore[arg-type]
        ik_link_pairs=len(ik.self_collision_pairs),
        ik_wall_pairs=len(ik.wall_pairs),
        touching_at_home=tuple(touching),
        hand=e_spec.hand.name,
        hand_joints=len(e_spec.hand.joints),
        finger_scales={f: round(float(s), 3) for f, s in scales.items()},
        upper_arm_links=e_spec.arm.upper_arm_links,
        forearm_links=e_spec.arm.forearm_links,
    )


def format_report(report: RobotReport) -> str:
    """The report as text for a terminal."""
    lines = [
        f"robot file {report.path}",
        f"  {report.description}",
        f"  layout (tasks and traces of): {report.layout or 'none'}",
        f"  tasks: {', '.join(report.tasks) or 'none'}",
        f"  check_env ({report.task_checked or 'no task'}): {report.check_env}",
    ]
    for f in report.effectors:
        lines += [
            f"effector {f.name} (side {f.side}): arm part {f.part}",
            f"  reach (upper bound: the links laid end to end, joint 1 to flange): {f.reach_m} m; flange at home "
            f"(world): {list(f.flange_home_world)}",
            f"  speed cap: {f.max_velocity_deg_s} deg/s; upper-arm links "
            f"{', '.join(f.upper_arm_links)}; forearm links {', '.join(f.forearm_links)}",
            "  joints (limits from the model, deg; home):",
            *(
                f"    {j}: [{lo}, {hi}]  home {h}"
                for j, (lo, hi), h in zip(f.joints, f.limits_deg, f.home_deg, strict=True)
            ),
            f"  IK collision pairs: {f.ik_link_pairs} link-link geom pairs, "
            f"{f.ik_wall_pairs} against the guard box's back wall",
            f"  touching at home: {', '.join(f.touching_at_home) or 'nothing'}",
            f"  hand {f.hand}: {f.hand_joints} joints; finger scales (human -> hand): "
            + ", ".join(f"{k} {v}" for k, v in f.finger_scales.items()),
        ]
    lines.append("missing: " + ("nothing" if not report.missing else ""))
    lines += [f"  - {m}" for m in report.missing]
    return "\n".join(lines)
