"""Differential inverse kinematics (mink) on a robot-only copy of the twin.

The IK model is the env's scene without task objects, so its joints are exactly the robot's
and the names match the env's action order. Each call moves the IK configuration one control
period towards the hand targets, under joint position and velocity limits: the result is a
joint trajectory a real arm can follow, never a jump.
"""

from __future__ import annotations

from collections.abc import Mapping

import mink
import mujoco
import numpy as np

from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.robots import Embodiment
from beavr_sim.robots.embodiment import BODY_PREFIX

#: Arm joint speed limit used by the IK (rad/s), well under the xArm7's 180 deg/s.
ARM_SPEED_LIMIT = 1.5
#: The body's joints hold (a speed limit of zero, to the solver's tolerance).
BODY_SPEED_LIMIT = 1e-9


class TwinIK:
    """Arm joint targets that put each effector's hand frame at a target pose."""

    def __init__(
        self,
        embodiment: Embodiment,
        dt: float,
        iterations: int = 2,
        position_cost: float = 1.0,
        orientation_cost: float = 0.5,
        posture_cost: float = 1e-2,
    ):
        self.embodiment = embodiment
        self.dt = float(dt)
        self.iterations = int(iterations)
        self.model = build_scene_spec(embodiment, 64, 64).compile()
        self.joints = embodiment.bind(self.model)
        self.configuration = mink.Configuration(self.model)
        self.frame_tasks = {
            e.name: mink.FrameTask(
                frame_name=e.name + "/hand",
                frame_type="body",
                position_cost=position_cost,
                orientation_cost=orientation_cost,
                lm_damping=1e-3,
            )
            for e in embodiment.effectors
        }
        self.posture_task = mink.PostureTask(self.model, cost=posture_cost)
        arm_joints = [j for e in embodiment.effectors for j in e.arm_joints]
        # The body (a humanoid's torso and head) holds its pose: the IK may not move it.
        speeds = {j: ARM_SPEED_LIMIT for j in arm_joints} | dict.fromkeys(
            embodiment.body_joints, BODY_SPEED_LIMIT
        )
        self.limits = [
            mink.ConfigurationLimit(self.model),
            mink.VelocityLimit(self.model, speeds),
        ]
        self._q = np.zeros(self.model.nq)
        self.reset(self.joints.home)
        # Geoms of each effector and of the body (a humanoid's torso and head), for reach
        # trials.
        body_name = [
            self.model.body(self.model.geom_bodyid[g]).name for g in range(self.model.ngeom)
        ]
        self._effector_geoms = {
            e.name: {g for g, b in enumerate(body_name) if b.startswith(e.name + "/")}
            for e in embodiment.effectors
        }
        self._body_geoms = {g for g, b in enumerate(body_name) if b.startswith(BODY_PREFIX)}
        self._trial = mujoco.MjData(self.model)

    def reset(self, q_action_order: np.ndarray, posture: np.ndarray | None = None) -> None:
        """Start from joint positions given in action order (e.g. the measured ones).

        ``posture`` (action order) is the configuration the redundancy resolves towards;
        by default the start itself.
        """
        self._q = self.configuration.q.copy()
        self._q[self.joints.qpos_adr] = q_action_order
        self.configuration.update(self._q)
        target = self._q.copy()
        if posture is not None:
            target[self.joints.qpos_adr] = posture
        self.posture_task.set_target(target)

    def converge(
        self, targets: Mapping[str, mink.SE3], seconds: float = 4.0, tolerance: float = 1e-3
    ) -> np.ndarray:
        """Run :meth:`step` until the hands reach ``targets`` (or ``seconds`` of steps pass).

        Returns the joint positions in action order; the IK state is left there.
        """
        for _ in range(int(np.ceil(seconds / self.dt))):
            q = self.step(targets)
            if max(p for p, _ in self.pose_error(targets).values()) < tolerance:
                break
        return q

    def reaches(
        self,
        *waypoints: Mapping[str, mink.SE3],
        position_tolerance: float = 0.005,
        rotation_tolerance: float = np.deg2rad(3.0),
    ) -> bool:
        """Whether the hands can get to each of ``waypoints`` (effector name -> target) in
        turn from the current configuration, without the arm running into the robot's body
        there (the IK does not avoid it): trial :meth:`converge` calls (joint limits
        included), after which the IK state is put back."""
        q, posture = self.configuration.q.copy(), self.posture_task.target_q.copy()
        try:
            for targets in waypoints:
                self.converge(targets)
                errors = self.pose_error(targets).values()
                if any(p > position_tolerance or r > rotation_tolerance for p, r in errors):
                    return False
                if any(self.touches_body(name) for name in targets):
                    return False
            return True
        finally:
            self.configuration.update(q)
            self.posture_task.set_target(posture)

    def touches_body(self, effector: str) -> bool:
        """Whether ``effector``'s arm or hand, in the current IK configuration, runs into the
        robot's body (a humanoid's torso or head; never, on arms without a body)."""
        own, body = self._effector_geoms[effector], self._body_geoms
        if not body:
            return False
        d = self._trial
        d.qpos[:] = self.configuration.q
        mujoco.mj_fwdPosition(self.model, d)
        return any(
            c.dist < 0
            and ((c.geom1 in own and c.geom2 in body) or (c.geom2 in own and c.geom1 in body))
            for c in d.contact[: d.ncon]
        )

    def T_world_hand(self, effector: str) -> mink.SE3:
        """The hand (mount) frame of ``effector`` in the current IK configuration."""
        return self.configuration.get_transform_frame_to_world(effector + "/hand", "body")

    def step(self, targets: Mapping[str, mink.SE3]) -> np.ndarray:
        """Advance one control period towards ``targets`` (effector name -> T_world_hand).

        Effectors without a target hold their pose. Returns the joint positions in action
        order (hand joints unchanged: the caller sets them).
        """
        tasks = [self.posture_task]
        for name, task in self.frame_tasks.items():
            task.set_target(targets[name] if name in targets else self.T_world_hand(name))
            tasks.append(task)
        sub_dt = self.dt / self.iterations
        for _ in range(self.iterations):
            velocity = mink.solve_ik(
                self.configuration, tasks, sub_dt, solver="daqp", damping=1e-4, limits=self.limits
            )
            self.configuration.integrate_inplace(velocity, sub_dt)
        return self.configuration.q[self.joints.qpos_adr].copy()

    def pose_error(self, targets: Mapping[str, mink.SE3]) -> dict[str, tuple[float, float]]:
        """Position (m) and rotation (rad) error of each targeted hand frame."""
        out = {}
        for name, target in targets.items():
            err = (target.inverse() @ self.T_world_hand(name)).log()
            out[name] = (float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:])))
        return out


def rotation_from_axes(fingers: np.ndarray, palm_normal: np.ndarray) -> np.ndarray:
    """R_world_hand with hand +z along ``fingers`` and +x along ``palm_normal``.

    ``palm_normal`` is made orthogonal to ``fingers``; both are world-frame directions.
    """
    z = np.asarray(fingers, float) / np.linalg.norm(fingers)
    x = np.asarray(palm_normal, float) - np.dot(palm_normal, z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def se3(R: np.ndarray, p: np.ndarray) -> mink.SE3:
    return mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(R), np.asarray(p, float))
