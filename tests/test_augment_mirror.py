"""A two-arm source mirrored left <-> right (``datasets augment``): the left hand placed at the
reflection of the right hand's pose, with the mirror's offset and finger signs, puts its
fingers where the right hand's reflected fingers are."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from beavr_sim.datasets.augment.mirror import M4, M, Mirror, _paired_hand_geoms
from beavr_sim.datasets.augment.replay import hand_body, hand_pose, make_env

#: xArm7 joints that turn the other way in the reflected arm (checked: the arms' home poses
#: are reflections, and with these signs so is every pose).
ARM_SIGNS = np.array([-1, 1, -1, 1, -1, 1, -1.0])


@pytest.fixture(scope="module")
def env():
    env = make_env("StackBlocks", "xarm7_leap_bimanual")
    yield env
    env.close()


def test_one_arm_has_no_mirror():
    env = make_env("PickPlace", "xarm7_leap_right")
    try:
        assert Mirror.of(env) is None
    finally:
        env.close()


def test_the_mirrored_hand_grasps_where_the_reflected_hand_did(env):
    mirror = Mirror.of(env)
    assert mirror is not None
    model, data = env.model, env.data
    geoms = _paired_hand_geoms(env)
    assert len(geoms["left"]) >= 15  # fingers and palm
    rng = np.random.default_rng(0)
    right, left = env.joints.slices["right"], env.joints.slices["left"]
    low, high = mirror.finger_range["right"]
    worst = 0.0
    for _ in range(5):
        q = env.joints.home.copy()
        q[right][:7] += rng.uniform(-0.3, 0.3, 7)
        q[right][7:] = rng.uniform(np.maximum(low, -0.3), np.minimum(high, 1.0))
        q[left][:7] = q[right][:7] * ARM_SIGNS
        q[left][7:] = q[right][7:] * mirror.finger_signs
        data.qpos[env.joints.qpos_adr] = q
        mujoco.mj_kinematics(model, data)
        T_left = hand_pose(env, hand_body(env, "left"))
        T_right = hand_pose(env, hand_body(env, "right"))
        assert np.allclose(T_left, M4 @ T_right @ M4, atol=1e-6)  # the arms are reflections
        # the left hand where the mirror puts it: its geoms, moved rigidly with the hand
        target = M4 @ T_right @ M4 @ mirror.offset["left"]
        moved = target @ np.linalg.inv(T_left)
        fingers = data.geom_xpos[geoms["left"]] @ moved[:3, :3].T + moved[:3, 3]
        wanted = data.geom_xpos[geoms["right"]] @ M.T
        worst = max(worst, float(np.abs(fingers - wanted).max()))
    assert worst < 0.005, f"mirrored fingers {worst * 1000:.1f} mm from the reflected ones"
