"""The operator's arm IK: mink on a one-effector copy of the twin, with collision avoidance.

Each effector gets its own robot-only model (its arm and hand at their base pose, and the
table), so effectors solve independently. One call to :meth:`ArmIK.step` moves the IK
configuration one control period towards the target hand pose, under

- joint position limits (``mink.ConfigurationLimit``),
- arm joint velocity limits (``mink.VelocityLimit``, ``ArmIKConfig.max_joint_speed``),
- collision avoidance (``mink.CollisionAvoidanceLimit``): hand and forearm against the table,
  hand against the upper arm and the base (self-collision).

The finger joints are not solved here; the caller sets them (the retargeted values) so the
collision geometry of the fingers is where the fingers are.
"""

from __future__ import annotations

from dataclasses import dataclass

import mink
import mujoco
import numpy as np

from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.robots.embodiment import Embodiment, EmbodimentSpec
from beavr_sim.teleop.collision import CollisionLimit

#: Arm links checked against the table, and arm links the hand must not hit.
FOREARM_LINKS = ("link5", "link6", "link7")
UPPER_ARM_LINKS = ("link_base", "link1", "link2", "link3")
#: Hand bodies whose geoms are checked: the palm and the four fingertips (the parts that
#: reach furthest; fewer pairs keep the IK well under a millisecond).
HAND_BODIES = ("palm", "thumb_distal", "index_distal", "middle_distal", "ring_distal")


@dataclass(frozen=True)
class ArmIKConfig:
    """Costs, limits and solver settings of the operator's arm IK."""

    position_cost: float = 1.0
    orientation_cost: float = 0.5
    posture_cost: float = 1e-2
    lm_damping: float = 1e-3
    damping: float = 1e-4
    max_joint_speed: float = 2.0  # rad/s, under the xArm7's 180 deg/s
    collision_margin: float = 0.005  # m kept between the checked geoms
    collision_detection: float = 0.03  # m at which avoidance starts acting
    collision_avoidance: bool = True
    iterations: int = 1
    solver: str = "daqp"

    def __post_init__(self) -> None:
        for name in ("position_cost", "orientation_cost", "max_joint_speed", "collision_detection"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")


def _body_geoms(model: mujoco.MjModel, body: str) -> list[int]:
    return [g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body(body).id]


class ArmIK:
    """Arm joint targets for one effector's hand pose target."""

    def __init__(
        self, embodiment: Embodiment, effector: str, dt: float, config: ArmIKConfig | None = None
    ):
        self.config = config or ArmIKConfig()
        self.dt = float(dt)
        name = embodiment.effector(effector).name  # raises with the valid names
        spec_e = next(e for e in embodiment.spec.effectors if e.name == name)
        self.single = Embodiment(EmbodimentSpec(f"{embodiment.name}:{effector}", (spec_e,)))
        self.effector = self.single.effectors[0]
        self.model = build_scene_spec(self.single, 64, 64).compile()
        self.joints = self.single.bind(self.model)
        self.n_arm = len(self.effector.arm_joints)
        self.configuration = mink.Configuration(self.model)
        self.frame_task = mink.FrameTask(
            frame_name=f"{effector}/hand",
            frame_type="body",
            position_cost=self.config.position_cost,
            orientation_cost=self.config.orientation_cost,
            lm_damping=self.config.lm_damping,
        )
        self.posture_task = mink.PostureTask(self.model, cost=self.config.posture_cost)
        self.limits: list = [
            mink.ConfigurationLimit(self.model),
            mink.VelocityLimit(
                self.model, {j: self.config.max_joint_speed for j in self.effector.arm_joints}
            ),
        ]
        if self.config.collision_avoidance:
            p = self.effector.name + "/"
            hand = [g for b in HAND_BODIES for g in _body_geoms(self.model, p + b)]
            palm = _body_geoms(self.model, p + "palm")
            forearm = [g for link in FOREARM_LINKS for g in _body_geoms(self.model, p + link)]
            upper = [g for link in UPPER_ARM_LINKS for g in _body_geoms(self.model, p + link)]
            table = [self.model.geom("table_top").id]
            self.limits.append(
                CollisionLimit(
                    self.model,
                    geom_pairs=[(hand + forearm, table), (palm, upper)],
                    minimum_distance_from_collisions=self.config.collision_margin,
                    collision_detection_distance=self.config.collision_detection,
                )
            )
        self.reset(self.joints.home)

    def reset(self, q_effector: np.ndarray, posture: np.ndarray | None = None) -> None:
        """Start from this effector's joint positions (arm then hand, action order)."""
        q = self.configuration.q.copy()
        q[self.joints.qpos_adr] = q_effector
        self.configuration.update(q)
        target = q.copy()
        if posture is not None:
            target[self.joints.qpos_adr] = posture
        self.posture_task.set_target(target)

    def set_fingers(self, q_hand: np.ndarray) -> None:
        """Put the finger joints where the hand command puts them (collision geometry)."""
        q = self.configuration.q.copy()
        q[self.joints.qpos_adr[self.n_arm :]] = q_hand
        self.configuration.update(q)

    @property
    def q(self) -> np.ndarray:
        """This effector's joint positions (arm then hand) in the IK configuration."""
        return self.configuration.q[self.joints.qpos_adr].copy()

    def T_world_hand(self) -> np.ndarray:
        return self.configuration.get_transform_frame_to_world(
            f"{self.effector.name}/hand", "body"
        ).as_matrix()

    def step(self, T_world_target: np.ndarray) -> np.ndarray:
        """One control period towards ``T_world_target``; returns the arm joint positions."""
        self.frame_task.set_target(mink.SE3.from_matrix(np.asarray(T_world_target)))
        tasks = [self.frame_task, self.posture_task]
        sub_dt = self.dt / self.config.iterations
        for _ in range(self.config.iterations):
            velocity = mink.solve_ik(
                self.configuration,
                tasks,
                sub_dt,
                solver=self.config.solver,
                damping=self.config.damping,
                limits=self.limits,
            )
            self.configuration.integrate_inplace(velocity, sub_dt)
        return self.configuration.q[self.joints.qpos_adr[: self.n_arm]].copy()
