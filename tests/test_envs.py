"""The gymnasium envs: registration, check_env, spaces, bad input, determinism, rendering."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import beavr_sim
from beavr_sim.envs.registration import env_id, registered_env_ids
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots import EMBODIMENTS
from beavr_sim.tasks.registry import TASKS, task_class

ENV_IDS = registered_env_ids()
BENCHMARK_TASKS = ("Tape", "Lantern", "StackBlocks", "FlipCube", "Pour", "PickPlace", "PickupBox")


def _supported(task: str) -> list[str]:
    allowed = task_class(task).embodiments
    return sorted(EMBODIMENTS) if allowed is None else list(allowed)


ENV_EMBODIMENTS = [(env_id(task), embodiment) for task in TASKS for embodiment in _supported(task)]


def test_registration_lists_every_task():
    assert "beavr_sim/Playground-v0" in ENV_IDS
    for task in BENCHMARK_TASKS:
        assert env_id(task) in ENV_IDS
    assert beavr_sim.register_envs() == ENV_IDS  # idempotent


def test_benchmark_tasks_support_the_issue_embodiments():
    for task in BENCHMARK_TASKS:
        assert "xarm7_leap_right" in _supported(task)
    for task in ("StackBlocks", "Pour", "PickPlace"):
        assert "xarm7_leap_bimanual" in _supported(task)


@pytest.mark.parametrize("env_id,embodiment", ENV_EMBODIMENTS)
def test_check_env_state_only(env_id, embodiment):
    env = gym.make(env_id, embodiment=embodiment)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_unsupported_embodiment_lists_the_supported_ones():
    with pytest.raises(UnknownNameError, match="xarm7_leap_right"):
        gym.make("beavr_sim/FlipCube-v0", embodiment="xarm7_leap_bimanual")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_check_env_with_cameras_and_render(env_id):
    env = gym.make(
        env_id,
        render_mode="rgb_array",
        cameras=["front", "overhead"],
        camera_height=48,
        camera_width=64,
    )
    check_env(env.unwrapped, skip_render_check=False)
    obs, _ = env.reset(seed=1)
    assert set(obs["pixels"]) == {"front", "overhead"}
    for image in obs["pixels"].values():
        assert image.shape == (48, 64, 3) and image.dtype == np.uint8
        assert image.std() > 5, "camera image is blank"
    frame = env.render()
    assert frame.shape == (48, 64, 3)
    env.close()


@pytest.mark.parametrize(
    "embodiment,n_joints",
    [("xarm7_leap_right", 23), ("xarm7_leap_left", 23), ("xarm7_leap_bimanual", 46)],
)
def test_spaces_and_introspection(embodiment, n_joints):
    env = gym.make("beavr_sim/Playground-v0", embodiment=embodiment)
    obs, info = env.reset(seed=0)
    assert obs["agent_pos"].shape == (n_joints,) and obs["agent_pos"].dtype == np.float32
    assert "pixels" not in obs
    assert env.action_space.shape == (n_joints,) and env.action_space.dtype == np.float32
    assert info["is_success"] is False
    u = env.unwrapped
    assert u.model.nu == n_joints and u.data.qpos.shape[0] == u.model.nq
    effectors = u.embodiment.effectors
    assert len(effectors) == n_joints // 23
    for eff in effectors:
        assert eff.side in ("left", "right")
        assert [j.split("/")[1] for j in eff.arm_joints] == [f"joint{i}" for i in range(1, 8)]
        assert [j.split("/")[1] for j in eff.hand_joints] == [f"leap_{i}" for i in range(16)]
        for site in (eff.ee_site, eff.palm_site, *eff.fingertip_sites):
            u.model.site(site)  # raises if missing
        assert len(eff.fingertip_sites) == 4
    # Home pose: BEAVR's xArm home in degrees, hand open.
    right = u.embodiment.effector("right") if embodiment != "xarm7_leap_left" else None
    if right is not None:
        sl = u.joints.slices["right"]
        np.testing.assert_allclose(
            np.rad2deg(obs["agent_pos"][sl][:7]), [0, -25, -1, 26, 0, 50, 0], atol=1e-4
        )
        np.testing.assert_allclose(obs["agent_pos"][sl][7:], 0.0, atol=1e-6)
    env.close()


def test_action_order_maps_one_to_one_to_joints():
    """Commanding one target moves that named joint (hardware order, not MuJoCo tree order)."""
    env = gym.make("beavr_sim/Playground-v0")
    obs, _ = env.reset(seed=0)
    names = env.unwrapped.joints.names
    # index abduction (motor 0) is moved away from the middle finger so nothing collides
    for joint, delta in (
        ("right/joint4", 0.3),
        ("right/leap_0", -0.3),
        ("right/leap_1", 0.3),
        ("right/leap_13", 0.3),
    ):
        i = names.index(joint)
        obs, _ = env.reset(seed=0)
        action = obs["agent_pos"].copy()
        action[i] += delta
        for _ in range(20):
            obs, *_ = env.step(action)
        moved = np.abs(obs["agent_pos"] - env.unwrapped.joints.home)
        assert np.argmax(moved) == i, f"{joint}: largest motion at {names[np.argmax(moved)]}"
        assert moved[i] == pytest.approx(abs(delta), abs=0.03)
        qpos = env.unwrapped.data.joint(joint).qpos[0]
        assert qpos == pytest.approx(obs["agent_pos"][i], abs=1e-6)


def test_holds_home_pose_without_contacts():
    env = gym.make("beavr_sim/Playground-v0", embodiment="xarm7_leap_bimanual")
    obs, _ = env.reset(seed=0)
    home = obs["agent_pos"].copy()
    for _ in range(60):
        obs, *_ = env.step(home)
    assert np.abs(obs["agent_pos"] - home).max() < 0.02
    assert env.unwrapped.data.ncon == 0, "robots at home should touch nothing"


def test_unknown_names_list_valid_choices():
    with pytest.raises(
        UnknownNameError, match=r"Did you mean 'xarm7_leap_right'.*xarm7_leap_bimanual"
    ):
        gym.make("beavr_sim/Playground-v0", embodiment="xarm7_leap_rigth")
    from beavr_sim.envs.beavr_env import BeavrEnv

    with pytest.raises(ValueError, match=r"Unknown task 'Playgrond'. Did you mean 'Playground'"):
        BeavrEnv(task="Playgrond")
    with pytest.raises(
        KeyError, match="Valid cameras for embodiment xarm7_leap_right: front, overhead"
    ):
        BeavrEnv(cameras=["wrist"])
    with pytest.raises(KeyError, match=r"Valid cameras .*: front, overhead"):
        BeavrEnv(cameras=["head"])  # the RX-1's camera; the xArm rig has none
    with pytest.raises(ValueError, match="render_mode"):
        BeavrEnv(render_mode="human")


def test_bad_actions_raise_and_out_of_range_is_clipped():
    env = gym.make("beavr_sim/Playground-v0")
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"expected \(23,\)"):
        env.step(np.zeros(22, np.float32))
    with pytest.raises(ValueError, match=r"expected \(23,\)"):
        env.step(np.zeros((1, 23), np.float32))
    bad = obs["agent_pos"].copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match=r"NaN/inf.*right/joint4"):
        env.step(bad)
    with pytest.raises(ValueError, match="numeric"):
        env.step("home")
    action = obs["agent_pos"].copy()
    _, _, _, _, info = env.step(action)
    assert info["action_clipped"] is False
    action_before_jump = action.copy()
    action[1] = 10.0  # joint2 upper limit is 2.0944
    _, _, _, _, info = env.step(action)
    assert info["action_clipped"] is True and info["clipped_joints"] == ("right/joint2",)
    # The clipped target is what the joint's servo follows (the xArm's interpolated servo,
    # envs/drive.py, moves its reference towards it at most at its speed cap).
    assert env.unwrapped.target[1] == pytest.approx(2.0944)
    servo = env.unwrapped._servo
    assert servo.target[1] == pytest.approx(2.0944)
    assert (
        abs(servo.reference[1] - action_before_jump[1]) <= np.pi / env.unwrapped.control_hz + 1e-9
    )


def _rollout(seed: int, steps: int = 40) -> np.ndarray:
    env = gym.make("beavr_sim/Playground-v0", embodiment="xarm7_leap_bimanual")
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    trace = [obs["agent_pos"]]
    for _ in range(steps):
        obs, *_ = env.step(env.action_space.sample())
        trace.append(obs["agent_pos"])
    env.close()
    return np.array(trace)


def test_same_seed_same_observations():
    a, b = _rollout(3), _rollout(3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, _rollout(4)), "different seeds should give different rollouts"


def test_time_limit_truncates_not_terminates():
    env = gym.make("beavr_sim/Playground-v0", control_hz=10, max_episode_seconds=0.5)
    obs, _ = env.reset(seed=0)
    flags = []
    for _ in range(5):
        obs, _, terminated, truncated, info = env.step(obs["agent_pos"])
        flags.append((terminated, truncated))
    assert flags[:4] == [(False, False)] * 4 and flags[4] == (False, True)
    assert info["elapsed_seconds"] == pytest.approx(0.5)


@pytest.mark.parametrize("control_hz", [30, 50, 7])
def test_control_period_is_exact(control_hz):
    u = gym.make("beavr_sim/Playground-v0", control_hz=control_hz).unwrapped
    assert u.model.opt.timestep * u.n_substeps == pytest.approx(1 / control_hz)
    assert u.model.opt.timestep <= 0.002


def test_advance_is_step_without_the_observation():
    """The twin steps with ``advance``: the same physics, success and info as ``step``."""
    from beavr_sim.envs.beavr_env import BeavrEnv

    envs = [BeavrEnv(task="Pour", embodiment="xarm7_leap_right") for _ in range(2)]
    try:
        for env in envs:
            env.reset(seed=3)
        rng = np.random.default_rng(0)
        home = envs[0].agent_pos.copy()
        for _ in range(5):
            action = (home + rng.normal(0.0, 0.05, home.shape)).astype(np.float32)
            _, reward, terminated, truncated, info = envs[0].step(action)
            assert envs[1].advance(action) == (terminated, truncated, info)
            np.testing.assert_array_equal(envs[0].data.qpos, envs[1].data.qpos)
            assert reward == float(info["is_success"])
    finally:
        for env in envs:
            env.close()
