"""beavr_sim inside LeRobot's own commands (``beavr_sim.integrations`` and ``plugins/``).

Unit tests of the env, robot and teleoperator configs and devices, then LeRobot's entry points
as subprocesses on tiny inputs, each feeding the next: ``lerobot-record`` (the bundled
PickupBox trace through ``--teleop.type=beavr_quest`` into ``--robot.type=beavr_sim``) ->
``LeRobotDataset`` -> ``lerobot-train`` with its periodic evaluation in ``--env.type=beavr_sim``
-> ``lerobot-eval`` of the checkpoint, and ``lerobot-replay`` of the recorded episode. Nothing
is downloaded (``HF_HUB_OFFLINE=1``, local paths, no pretrained backbone).
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")

from lerobot.envs.configs import EnvConfig
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig
from lerobot.utils.errors import DeviceNotConnectedError

from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.integrations.config_robot import BeavrSimRobotConfig
from beavr_sim.integrations.config_teleoperator import BeavrQuestTeleopConfig
from beavr_sim.integrations.env import BeavrSimEnvConfig
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots import make_embodiment

PLUGINS = ("lerobot_env_beavr_sim", "lerobot_robot_beavr_sim", "lerobot_teleoperator_beavr_sim")
REPO_ID = "beavr_sim/lerobot_record_test"
H, W = 48, 64  # tiny camera images
BIN = Path(sys.executable).parent


# ---------------------------------------------------------------------- plugins and registry
def test_plugin_distributions_are_named_as_lerobot_imports_them():
    # register_third_party_plugins imports the module named exactly as the metadata Name.
    names = {d.metadata["Name"] for d in importlib.metadata.distributions()}
    missing = [p for p in PLUGINS if p not in names]
    assert not missing, f"not installed (run make): {missing}; lerobot-like names: " + str(
        sorted(n for n in names if n.lower().startswith("lerobot"))
    )
    for name in PLUGINS:
        importlib.import_module(name)


def test_registry_round_trip_through_lerobots_parser_and_factories(tmp_path):
    from lerobot.envs.factory import make_env_config
    from lerobot.robots.utils import make_robot_from_config
    from lerobot.teleoperators.utils import make_teleoperator_from_config
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    assert EnvConfig.get_choice_class("beavr_sim") is BeavrSimEnvConfig
    assert RobotConfig.get_choice_class("beavr_sim") is BeavrSimRobotConfig
    assert TeleoperatorConfig.get_choice_class("beavr_quest") is BeavrQuestTeleopConfig

    env = make_env_config("beavr_sim", task="pick_place")
    assert env.type == "beavr_sim" and env.task == "PickPlace"
    assert env.gym_id == "beavr_sim/PickPlace-v0"

    import draccus

    @dataclasses.dataclass
    class Command:  # what lerobot-record parses
        robot: RobotConfig
        teleop: TeleoperatorConfig

    cmd = draccus.parse(
        Command,
        args=[
            "--robot.type=beavr_sim",
            "--robot.task=pickup_box",
            "--robot.camera_names=[front, overhead]",
            "--teleop.type=beavr_quest",
            "--teleop.source=trace",
            "--teleop.task=PickupBox",
            f"--robot.calibration_dir={tmp_path}",
            f"--teleop.calibration_dir={tmp_path}",
        ],
    )
    assert isinstance(cmd.robot, BeavrSimRobotConfig) and cmd.robot.task == "PickupBox"
    assert cmd.robot.camera_names == ["front", "overhead"]
    assert draccus.decode(BeavrSimRobotConfig, draccus.encode(cmd.robot)) == cmd.robot
    robot = make_robot_from_config(cmd.robot)
    teleop = make_teleoperator_from_config(cmd.teleop)
    assert type(robot).__name__ == "BeavrSimRobot" and not robot.is_connected
    assert type(teleop).__name__ == "BeavrQuestTeleop"
    assert teleop.embodiment.name == "xarm7_leap_right" and teleop.task == "PickupBox"
    assert teleop.action_features == robot.action_features


def test_import_beavr_sim_imports_no_lerobot():
    code = (
        "import sys, beavr_sim; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('lerobot', 'torch') "
        "or m.startswith('beavr_sim.integrations')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


# ---------------------------------------------------------------------- clear errors
def test_unknown_names_list_the_valid_choices():
    with pytest.raises(UnknownNameError, match="PickupBox") as err:
        BeavrSimEnvConfig(task="PickupBx")
    assert "Did you mean 'PickupBox'" in str(err.value)
    with pytest.raises(UnknownNameError, match="xarm7_leap_right"):
        BeavrSimEnvConfig(task="Tape", embodiment="rx1")  # Tape is one-armed
    with pytest.raises(UnknownNameError, match="front, overhead"):
        BeavrSimEnvConfig(task="Pour", cameras=["head"])  # the RX-1's camera
    with pytest.raises(ValueError, match="no environment_state"):
        BeavrSimEnvConfig(task="Playground", environment_state=True)
    with pytest.raises(UnknownNameError, match="xarm7_leap_bimanual"):
        BeavrSimRobotConfig(embodiment="xarm7")
    with pytest.raises(FileNotFoundError, match="sim, emulated"):
        BeavrSimRobotConfig(hardware="no_such_rig.toml")
    with pytest.raises(ValueError, match="dry_run needs hardware"):
        BeavrSimRobotConfig(dry_run=True)
    with pytest.raises(UnknownNameError, match="quest, trace, webxr"):
        BeavrQuestTeleopConfig(source="vr")
    with pytest.raises(ValueError, match=r"--teleop\.task"):
        BeavrQuestTeleopConfig(source="trace")
    with pytest.raises(ValueError, match="real clock"):
        BeavrQuestTeleopConfig(source="quest", clock="tick")
    with pytest.raises(FileNotFoundError):
        BeavrQuestTeleopConfig(source="trace", trace="missing.mcap")


# ---------------------------------------------------------------------- features
def test_env_and_robot_features_are_what_beavr_sim_datasets_records(tmp_path):
    from lerobot.envs.utils import env_to_policy_features
    from lerobot.utils.feature_utils import dataset_to_policy_features, hw_to_dataset_features

    from beavr_sim.integrations.robot import BeavrSimRobot

    for embodiment, cameras in (("xarm7_leap_bimanual", ("front",)), ("rx1", ("front", "head"))):
        recorded = lerobot_features(
            make_embodiment(embodiment),
            RecordingConfig(cameras=cameras, image_height=H, image_width=W, hand_keypoints=False),
        )
        env = BeavrSimEnvConfig(
            task="PickPlace",
            embodiment=embodiment,
            cameras=list(cameras),
            image_height=H,
            image_width=W,
        )
        assert env_to_policy_features(env) == dataset_to_policy_features(recorded)
        robot = BeavrSimRobot(
            BeavrSimRobotConfig(
                embodiment=embodiment,
                camera_names=list(cameras),
                image_height=H,
                image_width=W,
                calibration_dir=tmp_path,
            )
        )
        from_robot = {
            **hw_to_dataset_features(robot.observation_features, "observation", use_video=True),
            **hw_to_dataset_features(robot.action_features, "action"),
        }
        assert set(from_robot) == set(recorded)
        for key, feature in recorded.items():
            assert tuple(from_robot[key]["shape"]) == tuple(feature["shape"]), key
            if key in ("observation.state", "action"):
                assert list(from_robot[key]["names"]) == list(feature["names"]), key
    state = BeavrSimEnvConfig(task="PickupBox", cameras=[], environment_state=True)
    assert env_to_policy_features(state)["observation.environment_state"].shape[0] > 0


# ---------------------------------------------------------------------- the robot
@pytest.fixture(scope="module")
def sim_robot(tmp_path_factory):
    from beavr_sim.integrations.robot import BeavrSimRobot

    robot = BeavrSimRobot(
        BeavrSimRobotConfig(
            task="PickupBox",
            camera_names=["front"],
            image_height=H,
            image_width=W,
            calibration_dir=tmp_path_factory.mktemp("calibration"),
        )
    )
    robot.connect()
    yield robot
    if robot.is_connected:
        robot.disconnect()


def _joints(obs: dict, robot) -> dict[str, float]:
    return {k: obs[k] for k in robot.action_features}


def test_send_action_returns_what_the_guard_let_through(sim_robot):
    robot = sim_robot
    obs = robot.get_observation()
    assert obs["front"].shape == (H, W, 3) and obs["front"].dtype == np.uint8
    start = _joints(obs, robot)

    # A small, safe move is sent as commanded.
    safe = dict(start)
    safe["right/joint1"] += 0.02
    sent = robot.send_action(safe)
    assert robot.last_outcome.blocked == ()
    assert sent["right/joint1"] == pytest.approx(safe["right/joint1"])
    held = dict(sent)

    # Shoulder and elbow down into the table: refused, the arm keeps its last safe target.
    into_table = dict(held)
    into_table["right/joint2"], into_table["right/joint4"] = 1.5, 0.0
    for _ in range(3):
        sent = robot.send_action(into_table)
        assert robot.last_outcome.blocked == ("right",)
        assert sent != into_table
        assert sent["right/joint2"] == pytest.approx(held["right/joint2"])
        assert sent["right/joint4"] == pytest.approx(held["right/joint4"])
    measured = _joints(robot.get_observation(), robot)
    assert abs(measured["right/joint2"] - held["right/joint2"]) < 0.05
    assert robot.actions_refused >= 3


def test_send_action_rejects_malformed_actions(sim_robot):
    robot = sim_robot
    start = _joints(robot.get_observation(), robot)
    missing = {k: v for k, v in start.items() if k != "right/leap_3"}
    with pytest.raises(ValueError, match=r"missing joints right/leap_3.*Expected exactly"):
        robot.send_action(missing)
    with pytest.raises(ValueError, match="unknown keys left/joint1"):
        robot.send_action({**start, "left/joint1": 0.0})
    with pytest.raises(ValueError, match="non-finite targets for joints right/joint3"):
        robot.send_action({**start, "right/joint3": float("nan")})
    with pytest.raises(TypeError, match="dict of joint name"):
        robot.send_action(np.zeros(23))


def test_unconnected_devices_say_so(tmp_path):
    from beavr_sim.integrations.robot import BeavrSimRobot
    from beavr_sim.integrations.teleoperator import BeavrQuestTeleop

    robot = BeavrSimRobot(BeavrSimRobotConfig(calibration_dir=tmp_path))
    with pytest.raises(DeviceNotConnectedError, match="connect"):
        robot.get_observation()
    with pytest.raises(DeviceNotConnectedError):
        robot.disconnect()
    teleop = BeavrQuestTeleop(
        BeavrQuestTeleopConfig(source="trace", task="Pour", calibration_dir=tmp_path)
    )
    with pytest.raises(DeviceNotConnectedError, match="connect"):
        teleop.get_action()


def test_emulated_rig_runs_the_real_driver_paths(tmp_path):
    """hardware=emulated: the xArm SDK and the Dynamixel SDK against our emulators."""
    from beavr_sim.integrations.robot import BeavrSimRobot

    robot = BeavrSimRobot(
        BeavrSimRobotConfig(hardware="emulated", camera_names=[], calibration_dir=tmp_path)
    )
    robot.connect()
    try:
        assert robot.mirror is not None
        start = _joints(robot.get_observation(), robot)
        target = dict(start)
        target["right/joint1"] += 0.05
        target["right/leap_1"] += 0.1
        for _ in range(15):
            sent = robot.send_action(target)
        assert sent["right/joint1"] == pytest.approx(target["right/joint1"])
        import time

        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            measured = _joints(robot.get_observation(), robot)
            if abs(measured["right/joint1"] - target["right/joint1"]) < 0.01:
                break
            time.sleep(0.05)
        # Measured by the drivers from the emulated devices, not the twin's joints.
        assert measured["right/joint1"] == pytest.approx(target["right/joint1"], abs=0.01)
        assert measured["right/leap_1"] == pytest.approx(target["right/leap_1"], abs=0.05)
        summary = robot.mirror.summary()
        assert {"right_arm", "right_hand"} <= set(summary)
        # No action for a while (LeRobot saving an episode): the devices hold for want of a
        # command, and the next observation is still their measured joints, not an error.
        deadline = time.monotonic() + 30.0
        while not all(s["reason"] == "timeout" for s in robot.mirror.summary().values()):
            assert time.monotonic() < deadline, robot.mirror.summary()
            time.sleep(0.05)
        held = _joints(robot.get_observation(), robot)
        assert held["right/joint1"] == pytest.approx(target["right/joint1"], abs=0.01)
        robot.send_action(target)  # and the rig follows again
    finally:
        robot.disconnect()
    assert robot.mirror is None


def test_reset_scene_gives_the_mirrors_guard_the_new_fixtures(tmp_path):
    """hardware=emulated: at connect and after every reset_scene the mirror's own guard (the
    one that checks the devices' catch-up path) holds this layout's fixtures, not the
    model's defaults or the previous layout's."""
    from beavr_sim.integrations.robot import BeavrSimRobot

    robot = BeavrSimRobot(
        BeavrSimRobotConfig(
            task="Pour", hardware="emulated", camera_names=[], seed=0, calibration_dir=tmp_path
        )
    )
    robot.connect()
    try:
        guard, twin = robot.mirror.guard.data, robot.twin.env.data
        layouts = []
        for seed in (1, 2, None):
            np.testing.assert_array_equal(guard.mocap_pos, twin.mocap_pos)
            np.testing.assert_array_equal(guard.mocap_quat, twin.mocap_quat)
            layouts.append(twin.mocap_pos.copy())
            if seed is not None:
                robot.reset_scene(seed)
        assert not np.array_equal(layouts[0], layouts[1])  # (the cup moved)
        assert not np.array_equal(layouts[1], layouts[2])
    finally:
        robot.disconnect()


# ---------------------------------------------------------------------- the teleoperator
def test_teleoperator_plays_a_bundled_trace_on_the_tick_clock(tmp_path):
    from beavr_sim.integrations.teleoperator import BeavrQuestTeleop

    def run(n: int) -> list[dict[str, float]]:
        teleop = BeavrQuestTeleop(
            BeavrQuestTeleopConfig(source="trace", task="PickupBox", calibration_dir=tmp_path)
        )
        assert teleop.task == "PickupBox" and teleop.seed == 0  # from the trace's metadata
        teleop.connect()
        try:
            return [teleop.get_action() for _ in range(n)]
        finally:
            teleop.disconnect()

    actions = run(60)
    assert set(actions[0]) == set(make_embodiment("xarm7_leap_right").joint_names)
    first, last = np.array(list(actions[0].values())), np.array(list(actions[-1].values()))
    assert np.all(np.isfinite(last))
    assert np.abs(last - first).max() > 1e-3, "two seconds of the trace moved nothing"
    # The tick clock: the same trace gives the same actions however fast it is polled.
    again = run(60)
    assert again[-1] == actions[-1]


def test_teleoperator_and_sim_robot_complete_the_bundled_pickup_box_trace(tmp_path):
    """The plugin pair reproduces the native replay: every action of the bundled PickupBox
    trace passes the guard and the twin reports task success before the trace ends."""
    from beavr_sim.integrations.robot import BeavrSimRobot
    from beavr_sim.integrations.teleoperator import BeavrQuestTeleop

    robot = BeavrSimRobot(
        BeavrSimRobotConfig(task="PickupBox", camera_names=[], calibration_dir=tmp_path)
    )
    teleop = BeavrQuestTeleop(
        BeavrQuestTeleopConfig(source="trace", task="PickupBox", calibration_dir=tmp_path)
    )
    robot.connect()
    teleop.connect()
    try:
        env = robot.twin.env
        success_at = None
        for step in range(400):  # the trace is 9 s: 270 ticks at 30 Hz
            robot.send_action(teleop.get_action())
            if env.task.evaluate(env.model, env.data).success:
                success_at = step
                break
        assert success_at is not None, "the trace did not complete PickupBox"
        assert robot.actions_refused == 0
    finally:
        teleop.disconnect()
        robot.disconnect()


def test_teleoperator_serves_the_webxr_page_and_holds_without_a_headset(tmp_path):
    """``source=webxr``: the page is served on loopback, and with no headset connected every
    action is the home pose (the operator waits for hands; nothing moves)."""
    import urllib.request

    from beavr_sim.integrations.teleoperator import BeavrQuestTeleop

    with pytest.raises(ValueError, match="webxr host"):
        BeavrQuestTeleopConfig(source="webxr", webxr_host="*")
    with pytest.raises(ValueError, match="real clock"):
        BeavrQuestTeleopConfig(source="webxr", clock="tick")
    teleop = BeavrQuestTeleop(
        BeavrQuestTeleopConfig(
            source="webxr", task="PickupBox", webxr_port=0, calibration_dir=tmp_path
        )
    )
    teleop.connect()
    try:
        url = teleop.source.url
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=5) as response:
            assert response.status == 200
            assert b"Start" in response.read()
        first = teleop.get_action()
        for _ in range(5):
            action = teleop.get_action()
        assert action == first
        assert teleop.frames_received == 0
    finally:
        teleop.disconnect()


def test_teleoperator_takes_the_quest_apps_sockets(tmp_path):
    """source=quest: the bundled trace's right hand sent as the Quest app sends it (PUSH
    sockets, keypoint strings) to the teleoperator's sockets, on free ports."""
    import time

    import zmq

    from beavr_sim.assets import bundled_trace
    from beavr_sim.headset.quest_protocol import format_keypoints
    from beavr_sim.headset.sources import TraceSource
    from beavr_sim.integrations.config_teleoperator import QUEST_PORTS
    from beavr_sim.integrations.teleoperator import BeavrQuestTeleop
    from beavr_sim.wire.ports import PortConfig

    free = PortConfig.free()
    config = BeavrQuestTeleopConfig(
        source="quest",
        task="PickupBox",
        quest_ports=[free.port(n) for n in QUEST_PORTS],
        calibration_dir=tmp_path,
    )
    with pytest.raises(ValueError, match="quest_right, quest_left"):
        dataclasses.replace(config, quest_ports=[1, 2])
    frames = [f for f in TraceSource(bundled_trace("PickupBox")).frames if f.side == "right"]
    teleop = BeavrQuestTeleop(config)
    teleop.connect()
    context = zmq.Context()
    push = context.socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    push.connect(config.transport().endpoint("quest_right", bind=False))
    try:
        actions = []
        for frame in frames[:75]:
            push.send_string(format_keypoints(frame))
            time.sleep(1 / 30)
            actions.append(teleop.get_action())
        assert teleop.source.receiver is not None and teleop.operator is not None
        first, last = np.array(list(actions[0].values())), np.array(list(actions[-1].values()))
        assert np.abs(last - first).max() > 1e-3, "the headset's frames moved nothing"
    finally:
        push.close()
        context.destroy(linger=0)
        teleop.disconnect()


# ---------------------------------------------------------------------- LeRobot's commands
def _cli(name: str, args: list[str], home: Path, timeout: float) -> str:
    exe = BIN / name
    if not exe.exists():
        pytest.skip(f"{name} is not installed beside this Python")
    env = {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_LEROBOT_HOME": str(home),
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }
    result = subprocess.run(
        [str(exe), *args], capture_output=True, text=True, timeout=timeout, env=env, cwd=home
    )
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"{name} failed:\n{output[-4000:]}"
    return output


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("lerobot_cli")


@pytest.fixture(scope="module")
def recorded(workdir) -> Path:
    """One short episode: the bundled PickupBox trace -> teleoperator -> sim robot."""
    root = workdir / "dataset"
    _cli(
        "lerobot-record",
        [
            "--robot.type=beavr_sim",
            "--robot.task=PickupBox",
            "--robot.camera_names=[front]",
            f"--robot.image_height={H}",
            f"--robot.image_width={W}",
            "--teleop.type=beavr_quest",
            "--teleop.source=trace",
            "--teleop.task=PickupBox",
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={root}",
            "--dataset.num_episodes=1",
            "--dataset.episode_time_s=1",
            "--dataset.fps=30",
            "--dataset.single_task=Pick up the box and put it down in the green area.",
            "--dataset.push_to_hub=false",
            "--dataset.video=false",
            "--play_sounds=false",
        ],
        workdir,
        timeout=180,
    )
    return root


def test_lerobot_record_writes_a_dataset_lerobot_reads(recorded):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=recorded)
    assert ds.num_episodes == 1 and len(ds) >= 5
    assert ds.meta.robot_type == "beavr_sim"
    names = list(make_embodiment("xarm7_leap_right").joint_names)
    assert ds.features["observation.state"]["names"] == names
    assert ds.features["action"]["names"] == names
    item = ds[len(ds) - 1]
    assert tuple(item["observation.images.front"].shape) == (3, H, W)
    assert tuple(item["observation.state"].shape) == (23,)
    assert np.isfinite(item["action"].numpy()).all()


@pytest.fixture(scope="module")
def checkpoint(recorded, workdir) -> tuple[Path, str]:
    """One ACT step with lerobot-train, evaluating in --env.type=beavr_sim at that step."""
    out = workdir / "train"
    log = _cli(
        "lerobot-train",
        [
            "--policy.type=act",
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={recorded}",
            "--dataset.video_backend=pyav",
            "--steps=1",
            "--batch_size=2",
            "--num_workers=0",
            "--policy.device=cpu",
            "--policy.push_to_hub=false",
            "--policy.pretrained_backbone_weights=null",
            "--policy.chunk_size=5",
            "--policy.n_action_steps=5",
            "--policy.dim_model=32",
            "--policy.dim_feedforward=64",
            "--policy.n_heads=2",
            "--policy.n_encoder_layers=1",
            "--wandb.enable=false",
            "--save_freq=1",
            "--log_freq=1",
            "--env.type=beavr_sim",
            "--env.task=PickupBox",
            "--env.cameras=[front]",
            f"--env.image_height={H}",
            f"--env.image_width={W}",
            "--env.episode_length=4",
            "--env_eval_freq=1",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={out}",
        ],
        workdir,
        timeout=300,
    )
    return out / "checkpoints" / "last" / "pretrained_model", log


def test_lerobot_train_evaluates_in_the_beavr_sim_env(checkpoint, workdir):
    model, log = checkpoint
    assert (model / "model.safetensors").is_file()
    assert "'pc_success': 0.0" in log or "'pc_success': 100.0" in log, log[-3000:]
    videos = list((workdir / "train" / "eval").rglob("*.mp4"))
    assert videos and all(v.stat().st_size > 0 for v in videos)
    config = json.loads((model / "config.json").read_text())
    assert set(config["input_features"]) == {"observation.state", "observation.images.front"}


def test_lerobot_eval_runs_the_trained_policy(checkpoint, workdir):
    model, _ = checkpoint
    out = workdir / "eval"
    _cli(
        "lerobot-eval",
        [
            f"--policy.path={model}",
            "--policy.device=cpu",
            "--env.type=beavr_sim",
            "--env.task=pickup_box",
            "--env.cameras=[front]",
            f"--env.image_height={H}",
            f"--env.image_width={W}",
            "--env.episode_length=6",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={out}",
        ],
        workdir,
        timeout=180,
    )
    info = json.loads((out / "eval_info.json").read_text())
    overall = info["overall"]
    assert overall["n_episodes"] == 1 and overall["pc_success"] in (0.0, 100.0)
    videos = list(out.rglob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0


def test_lerobot_replay_plays_the_episode_on_the_sim_robot(recorded, workdir, monkeypatch):
    """LeRobot's replay (its ``replay`` function, in this process: the CLI adds only the
    plugin import and argument parsing, exercised by lerobot-record above)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.scripts.lerobot_replay import DatasetReplayConfig, ReplayConfig, replay

    from beavr_sim.integrations.robot import BeavrSimRobot

    robots: list[BeavrSimRobot] = []
    sent: list[dict[str, float]] = []
    connect, send_action = BeavrSimRobot.connect, BeavrSimRobot.send_action

    def connect_spy(self, calibrate: bool = True) -> None:
        robots.append(self)
        connect(self, calibrate)

    def send_spy(self, action):
        sent.append(send_action(self, action))
        return sent[-1]

    monkeypatch.setattr(BeavrSimRobot, "connect", connect_spy)
    monkeypatch.setattr(BeavrSimRobot, "send_action", send_spy)
    ds = LeRobotDataset(REPO_ID, root=recorded)
    replay(
        ReplayConfig(
            robot=BeavrSimRobotConfig(
                task="PickupBox", camera_names=[], calibration_dir=workdir / "calibration"
            ),
            dataset=DatasetReplayConfig(repo_id=REPO_ID, root=recorded, episode=0, fps=30),
            play_sounds=False,
        )
    )
    (robot,) = robots
    assert not robot.is_connected and robot.actions_sent == len(ds) == len(sent)
    recorded_actions = np.array(ds.hf_dataset["action"], dtype=np.float64)
    names = ds.features["action"]["names"]
    replayed = np.array([[a[n] for n in names] for a in sent])
    if robot.actions_refused == 0:  # what the guard let through is what was recorded
        np.testing.assert_allclose(replayed, recorded_actions, atol=1e-5)
    else:
        assert np.isfinite(replayed).all()


def test_lerobot_record_on_an_emulated_rig_keeps_its_true_episodes_and_ends_at_a_dead_device(
    tmp_path,
):
    """A whole ``lerobot-record`` session on the emulated rig (the xArm SDK and the Dynamixel
    SDK against our emulators), the bundled PickupBox trace driving it, episodes of 1 s until
    the LEAP hand stops answering for good (20 s after the emulators start): the session ends
    on one line naming the hand, the episodes saved before it are kept and their measured
    state follows their commands by the rig's rule, and the episode in progress is not saved
    (no frozen measured state recorded as live)."""
    from recorded_state import check_within_rule, read_episodes

    exe = BIN / "lerobot-record"
    if not exe.exists():
        pytest.skip("lerobot-record is not installed beside this Python")
    root, repo_id, episodes = tmp_path / "rig_ds", "local/emulated_rig", 60
    args = [
        "--robot.type=beavr_sim",
        "--robot.task=PickupBox",
        "--robot.hardware=emulated",
        "--robot.emulate_faults=right_hand:disconnect@20",
        "--robot.camera_names=[]",
        "--teleop.type=beavr_quest",
        "--teleop.source=trace",
        "--teleop.task=PickupBox",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        f"--dataset.num_episodes={episodes}",
        "--dataset.episode_time_s=1",
        "--dataset.reset_time_s=0",
        "--dataset.fps=30",
        "--dataset.single_task=Pick up the box and put it down in the green area.",
        "--dataset.push_to_hub=false",
        "--dataset.video=false",
        "--play_sounds=false",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_LEROBOT_HOME": str(tmp_path)}
    result = subprocess.run(
        [str(exe), *args], capture_output=True, text=True, timeout=240, env=env, cwd=tmp_path
    )
    output = result.stdout + result.stderr
    assert result.returncode != 0, f"the session outlived its dead hand:\n{output[-3000:]}"
    errors = [line for line in output.splitlines() if "MeasuredStateError:" in line]
    assert errors, f"no MeasuredStateError:\n{output[-3000:]}"
    # Named by the device (its outage) or by one of its joints (the state rule, had the
    # outage come later than the window on a busy machine).
    assert re.search(r"right_hand|right/leap_", errors[-1]), errors[-1]
    assert "check the rig" in errors[-1], errors[-1]

    saved = read_episodes(root, repo_id)
    assert 1 <= len(saved) < episodes, len(saved)
    for episode, (state, action, names) in saved.items():
        assert len(state) >= 20, (episode, len(state))  # whole episodes of 1 s, none cut
        check_within_rule(state, action, names, episode)
        assert np.isfinite(state).all()


def test_robot_refuses_a_measured_state_that_stays_away_or_a_device_not_live(tmp_path):
    """The robot judges its measured joints by the rig's rule (the teleop recorder's watch):
    a reading frozen while the commands move on passes for less than the window, then
    ``send_action`` raises one line naming the joint; a device not live fails
    ``get_observation`` before any state is handed out. (A sim robot given a watch over a
    frozen reading: the rule, not the devices, is under test here.)"""
    import time

    from beavr_sim.datasets.recorder import FollowLimits, HardwareWatch
    from beavr_sim.hardware.device import MeasuredStateError
    from beavr_sim.hardware.mirror import Reading
    from beavr_sim.integrations.robot import BeavrSimRobot

    class Health:
        def __init__(self, live: bool, faults: tuple[str, ...] = ()):
            self.live, self.devices, self.episode_faults = live, (), faults

    robot = BeavrSimRobot(
        BeavrSimRobotConfig(task="PickupBox", camera_names=[], calibration_dir=tmp_path)
    )
    robot.connect()
    try:
        names = robot.joint_names
        frozen = robot.measured_positions()
        limits = FollowLimits(np.full(len(names), 0.3), 0.5, names, lag_s=0.25)
        health = Health(True)
        robot.watch = HardwareWatch(
            lambda: Reading(frozen, time.monotonic(), "right_arm"), lambda: health, limits, 30
        )
        robot.watch.begin()
        j = names.index("right/joint1")
        frames = 0
        with pytest.raises(MeasuredStateError) as raised:
            for frames in range(1, 200):
                obs = robot.get_observation()
                target = {n: obs[n] for n in names}
                target["right/joint1"] = frozen[j] + 0.02 * frames  # the command moves on
                robot.send_action(target)
        message = str(raised.value)
        assert "\n" not in message and "right/joint1" in message and "not recorded" in message
        # 0.3 rad away after 15 frames (and the lag's 8), then the 0.5 s window (15 frames).
        assert 15 + 15 <= frames <= 15 + 8 + 17, frames

        robot.watch.begin()
        health.live, health.devices = False, ()
        health.episode_faults = ("right_hand stopped answering",)
        with pytest.raises(MeasuredStateError, match="hardware not live: right_hand stopped"):
            robot.get_observation()
    finally:
        robot.disconnect()
