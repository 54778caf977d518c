"""Success checkers of Lantern, Tape and Pour on constructed states, near misses included."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.tasks import lantern, pour, tape
from beavr_sim.tasks.checks import REST_SECONDS, in_contact
from beavr_sim.tasks.objects import yaw_quat
from beavr_sim.workcell import TABLE_TOP_Z

TASKS = ("Lantern", "Tape", "Pour")
#: An arm pose (joint2, joint4, joint6 in degrees; others at home) with the fingertips pointing
#: down about 28 cm above the table, high enough to hold an object lifted off the table.
RAISED_ARM_DEG = {1: -25.0, 3: 60.0, 5: 85.0}


def make(task: str, seed: int = 0):
    env = gym.make(f"beavr_sim/{task}-v0").unwrapped
    env.reset(seed=seed)
    return env


def hold(env, seconds: float) -> list[dict]:
    """Step with the arm holding its current pose; the info of every step."""
    action = env.agent_pos
    return [env.step(action)[4] for _ in range(round(seconds * env.control_hz))]


def up(z: float) -> np.ndarray:
    return np.array([0.0, 0.0, z])


def quat_about_x(deg: float) -> np.ndarray:
    half = np.deg2rad(deg) / 2
    return np.array([np.cos(half), np.sin(half), 0.0, 0.0])


def raise_arm(env) -> None:
    q = env.joints.home.copy()
    for i, deg in RAISED_ARM_DEG.items():
        q[i] = np.deg2rad(deg)
    env.data.qpos[env.joints.qpos_adr] = q
    mujoco.mj_forward(env.model, env.data)


def arm_home(env) -> None:
    env.data.qpos[env.joints.qpos_adr] = env.joints.home
    env.data.qvel[env.joints.qvel_adr] = 0.0


def box_top(env) -> np.ndarray:
    """World position of the centre of the box top."""
    return env.task.fixtures["box"].pos(env.data) + up(2 * lantern.BOX_HALF[2])


def index_tip_capsule(env) -> tuple[np.ndarray, float]:
    """The index fingertip capsule: its lower end point (world) and its radius."""
    model, data = env.model, env.data
    body = model.body("right/index_distal").id
    (g,) = [
        g
        for g in np.flatnonzero(model.geom_bodyid == body)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE
    ]
    axis = data.geom_xmat[g].reshape(3, 3)[:, 2]
    end = data.geom_xpos[g] - np.sign(axis[2]) * model.geom_size[g, 1] * axis
    return end, float(model.geom_size[g, 0])


@pytest.mark.parametrize("task", TASKS)
def test_check_env(task):
    env = gym.make(f"beavr_sim/{task}-v0")
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.parametrize("task", TASKS)
def test_zero_motion_never_succeeds(task):
    for seed in (0, 1):
        env = make(task, seed)
        infos = hold(env, 2.0)
        assert not any(i["is_success"] or i["is_failure"] for i in infos)
        assert not any(env.task.touched_by_robot(env.model, env.data, n) for n in env.task.objects)


# --------------------------------------------------------------------------- Lantern
def place_lantern_on_box(env, quat=(1.0, 0.0, 0.0, 0.0), centre_height=lantern.LANTERN_HALF_HEIGHT):
    env.task.objects["lantern"].set_pose(env.data, box_top(env) + up(centre_height + 0.001), quat)
    mujoco.mj_forward(env.model, env.data)


def lift_lantern_against_index_tip(env, by: str) -> None:
    """Arm raised; the lantern hangs with its handle bar (or its glass) against the index tip."""
    raise_arm(env)
    end, tip_radius = index_tip_capsule(env)
    lantern_body = env.task.objects["lantern"]
    if by == "handle":
        bar_z = lantern.LANTERN_HALF_HEIGHT + lantern.HANDLE_CLEARANCE + lantern.HANDLE_RADIUS
        centre = end + up(0.002 - tip_radius - lantern.HANDLE_RADIUS - bar_z)
        lantern_body.set_pose(env.data, centre)  # bar along world x, under the tip
    else:  # the glass pressed against the side of the tip, handle turned away from the hand
        offset = lantern.GLASS_RADIUS + tip_radius - 0.002
        lantern_body.set_pose(env.data, end + np.array([offset, 0.0, -0.03]), yaw_quat(np.pi / 2))
    mujoco.mj_forward(env.model, env.data)


def test_lantern_latch_set_only_when_lifted_by_the_handle():
    env = make("Lantern")
    task, model, data = env.task, env.model, env.data
    robot = task.robot_geoms

    task.check(model, data)  # on the table, untouched
    assert not task.lifted_by_handle

    lift_lantern_against_index_tip(env, by="body")
    assert in_contact(model, data, task.body_geoms, robot)
    lifted_z = TABLE_TOP_Z + lantern.LANTERN_HALF_HEIGHT + lantern.LIFT_HEIGHT
    assert task.objects["lantern"].pos(data)[2] >= lifted_z
    task.check(model, data)
    assert not task.lifted_by_handle

    lift_lantern_against_index_tip(env, by="handle")
    assert task.objects["lantern"].pos(data)[2] >= lifted_z
    assert in_contact(model, data, task.handle_geoms, robot)
    assert not in_contact(model, data, task.body_geoms, robot)
    task.check(model, data)
    assert task.lifted_by_handle

    arm_home(env)
    place_lantern_on_box(env)
    infos = hold(env, 1.0)
    assert infos[-1]["is_success"], infos[-1]


def test_lantern_lifted_by_the_body_then_on_box_fails():
    env = make("Lantern")
    lift_lantern_against_index_tip(env, by="body")
    env.task.check(env.model, env.data)
    arm_home(env)
    place_lantern_on_box(env)
    info = hold(env, 1.0)[-1]
    assert not info["is_success"]
    assert info["task/on_box"] and info["task/upright"] and info["task/at_rest"]
    assert not info["task/lifted_by_handle"]


def test_lantern_lying_on_box_fails():
    env = make("Lantern")
    env.task.lifted_by_handle = True
    place_lantern_on_box(env, quat_about_x(90.0), centre_height=lantern.LANTERN_RADIUS)
    info = hold(env, 1.0)[-1]
    assert not info["is_success"]
    assert info["task/on_box"] and info["task/over_box"] and not info["task/upright"]


def test_lantern_not_at_rest_fails_until_still():
    env = make("Lantern")
    env.task.lifted_by_handle = True
    place_lantern_on_box(env, centre_height=lantern.LANTERN_HALF_HEIGHT + 0.01)
    lantern_body = env.task.objects["lantern"]
    env.data.qvel[lantern_body.qvel_adr : lantern_body.qvel_adr + 3] = (0.1, 0.0, -0.3)
    infos = hold(env, REST_SECONDS - 0.1)
    assert not any(i["is_success"] for i in infos)
    assert not infos[0]["task/at_rest"]
    assert hold(env, 1.0)[-1]["is_success"]


# ------------------------------------------------------------------------------ Tape
def ring_tip(env) -> np.ndarray:
    return env.data.site("right/ring_tip").xpos.copy()


def place_tape(env, centre, quat=(1.0, 0.0, 0.0, 0.0)) -> None:
    env.task.objects["tape"].set_pose(env.data, centre, quat)
    mujoco.mj_forward(env.model, env.data)


def place_tape_on_box(env) -> None:
    place_tape(env, box_top(env) + up(tape.TAPE_HALF_WIDTH + 0.001))


def test_tape_latch_set_only_with_ring_finger_in_hole():
    env = make("Tape")
    task, model, data = env.task, env.model, env.data
    tip = ring_tip(env)  # the arm at home: the tip is 7 cm above the table
    assert tip[2] >= TABLE_TOP_Z + tape.TAPE_HALF_WIDTH + tape.LIFT_HEIGHT

    task.check(model, data)  # on the table
    assert not task.lifted_with_finger

    # Lifted, the ring tip pinching the roll from outside: just beyond its outer face.
    place_tape(env, tip - np.array([tape.TAPE_OUTER_RADIUS + 0.01, 0.0, 0.0]))
    task.check(model, data)
    assert not task.ring_tip_in_hole(data) and not task.lifted_with_finger

    # Lifted, the ring tip over the hole but above the roll's height band.
    place_tape(env, tip - up(tape.TAPE_HALF_WIDTH + tape.IN_HOLE_Z_MARGIN + 0.005))
    task.check(model, data)
    assert not task.ring_tip_in_hole(data) and not task.lifted_with_finger

    # Lifted, the ring tip in the hole, near its wall and tilted with the roll.
    place_tape(env, tip - np.array([tape.TAPE_INNER_RADIUS - 0.01, 0.0, 0.0]), quat_about_x(30.0))
    task.check(model, data)
    assert task.ring_tip_in_hole(data) and task.lifted_with_finger

    place_tape_on_box(env)
    infos = hold(env, 1.0)
    assert infos[-1]["is_success"], infos[-1]


def test_tape_lifted_without_finger_then_on_box_fails():
    env = make("Tape")
    place_tape(env, ring_tip(env) - np.array([tape.TAPE_OUTER_RADIUS + 0.01, 0.0, 0.0]))
    env.task.check(env.model, env.data)
    place_tape_on_box(env)
    info = hold(env, 1.0)[-1]
    assert not info["is_success"]
    assert info["task/on_box"] and info["task/over_box"] and info["task/at_rest"]


def test_tape_on_table_fails():
    env = make("Tape")
    env.task.lifted_with_finger = True
    info = hold(env, 1.0)[-1]
    assert not info["is_success"]
    assert not info["task/on_box"] and info["task/at_rest"]


def test_tape_sliding_on_box_fails_until_still():
    env = make("Tape")
    env.task.lifted_with_finger = True
    place_tape_on_box(env)
    roll = env.task.objects["tape"]
    env.data.qvel[roll.qvel_adr : roll.qvel_adr + 6] = (0.05, 0.0, 0.0, 0.0, 0.0, 4.0)
    infos = hold(env, REST_SECONDS - 0.1)
    assert not any(i["is_success"] for i in infos)
    assert not infos[0]["task/at_rest"]
    assert hold(env, 1.0)[-1]["is_success"]


# ------------------------------------------------------------------------------ Pour
def target_cup_points(env, n: int, lift: float = 0.0) -> list[np.ndarray]:
    """``n`` drop positions stacked in the target cup (2 x 2 per layer), raised by ``lift``."""
    base = env.task.fixtures["target_cup"].pos(env.data)
    return [base + offset + up(lift) for offset in pour.particle_offsets()[:n]]


def put_drops(env, points) -> None:
    for particle, point in zip(env.task.particles, points, strict=False):
        particle.set_pose(env.data, point)
    mujoco.mj_forward(env.model, env.data)


def test_pour_drops_settle_in_source_cup():
    env = make("Pour", seed=3)
    source = env.task.objects["source_cup"]
    for info in hold(env, 1.0):
        assert info["task/held_by_source"] == pour.N_PARTICLES and info["task/poured"] == 0
    assert max(p.linear_speed(env.data) for p in env.task.particles) < 0.02
    assert source.linear_speed(env.data) < 0.02


@pytest.mark.parametrize("n_in_target", [pour.MIN_POURED - 1, pour.MIN_POURED])
def test_pour_counts_half_of_the_drops(n_in_target):
    env = make("Pour")
    source_pos = env.task.objects["source_cup"].pos(env.data)
    in_source = [source_pos + o for o in pour.particle_offsets()[n_in_target:]]
    put_drops(env, target_cup_points(env, n_in_target) + in_source)
    status = env.task.evaluate(env.model, env.data)
    assert status.details["poured"] == n_in_target
    assert status.success is (n_in_target >= pour.MIN_POURED)


@pytest.mark.parametrize("n_dropped", [pour.MIN_POURED - 1, pour.MIN_POURED])
def test_pour_drops_falling_into_target_are_counted_once_settled(n_dropped):
    env = make("Pour")
    source_pos = env.task.objects["source_cup"].pos(env.data)
    in_source = [source_pos + o for o in pour.particle_offsets()[n_dropped:]]
    dropped = target_cup_points(env, n_dropped, lift=pour.TARGET_HEIGHT)
    put_drops(env, dropped + in_source)
    info = hold(env, 1.0)[-1]
    assert info["task/poured"] == n_dropped
    assert info["is_success"] is (n_dropped >= pour.MIN_POURED)


def test_pour_source_cup_tipped_over_with_drops_spilled_fails():
    env = make("Pour")
    target_xy = env.task.fixtures["target_cup"].pos(env.data)[:2]
    source = env.task.objects["source_cup"]
    source_xy = source.pos(env.data)[:2]
    source.set_pose(
        env.data, (*source_xy, TABLE_TOP_Z + pour.SOURCE_OUTER_RADIUS), quat_about_x(90)
    )
    # Spilled on the table beyond the tipped cup's rim, away from the target.
    away = source_xy - target_xy
    away /= np.linalg.norm(away)
    spill = [
        np.array([*(source_xy + (0.12 + 0.02 * i) * away), TABLE_TOP_Z + pour.PARTICLE_RADIUS])
        for i in range(pour.N_PARTICLES)
    ]
    put_drops(env, spill)
    info = hold(env, 0.5)[-1]
    assert not info["is_success"] and not info["is_failure"]
    assert info["task/poured"] == 0 and info["task/held_by_source"] == 0


def test_pour_source_cup_set_inside_target_does_not_count():
    env = make("Pour")
    base = env.task.fixtures["target_cup"].pos(env.data) + up(pour.CUP_WALL)
    env.task.objects["source_cup"].set_pose(env.data, base)
    put_drops(env, [base + o for o in pour.particle_offsets()])
    status = env.task.evaluate(env.model, env.data)
    assert not status.success
    assert status.details["poured"] == 0
    assert status.details["held_by_source"] == pour.N_PARTICLES
