"""LeRobot datasets from teleoperation: features, generation through the pipeline, loading with
LeRobot, crash safety (SIGKILL mid-episode), and lerobot-train on the result."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from waiting import HANG_GUARD_S

from beavr_sim.datasets.features import (
    ACTION,
    KEYPOINTS,
    STATE,
    TRACKED,
    RecordingConfig,
    lerobot_features,
)
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots import make_embodiment

lerobot = pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

REPO_ID = "test/pickup_box"
TINY = RecordingConfig(cameras=("front",), image_height=48, image_width=64)


def test_features_follow_the_embodiment():
    right = lerobot_features(make_embodiment("xarm7_leap_right"), RecordingConfig())
    assert right[STATE]["shape"] == right[ACTION]["shape"] == (23,)
    assert right[STATE]["names"][0].endswith("joint1")
    assert right["observation.images.front"]["shape"] == (480, 640, 3)
    assert right[KEYPOINTS]["shape"] == (26 * 3,) and right[TRACKED]["shape"] == (26,)
    both = lerobot_features(make_embodiment("xarm7_leap_bimanual"), RecordingConfig(cameras=()))
    assert both[STATE]["shape"] == (46,) and both[KEYPOINTS]["shape"] == (2 * 26 * 3,)
    assert not any(k.startswith("observation.images.") for k in both)


def test_recording_config_rejects_bad_values():
    with pytest.raises(UnknownNameError, match="overhead"):
        RecordingConfig(cameras=("side",))
    with pytest.raises(ValueError, match="fps"):
        RecordingConfig(fps=0)
    with pytest.raises(ValueError, match="image size"):
        RecordingConfig(image_height=0)
    # Too small for the video encoder, which would kill the process rather than raise.
    with pytest.raises(ValueError, match=r"16x16 \(HxW\) is too small to record as video"):
        RecordingConfig(cameras=("front",), image_height=16, image_width=16)
    RecordingConfig(cameras=("front",), image_height=16, image_width=16, use_videos=False)
    RecordingConfig(cameras=(), image_height=16, image_width=16)  # no camera: nothing encoded
    RecordingConfig(cameras=("front",), image_height=24, image_width=32)  # the tests' size


def test_the_writer_refuses_a_video_the_encoder_would_crash_on(tmp_path):
    """A video feature 16 wide (a real camera's, the robot plugin's) is refused with one line
    before anything is written; SVT-AV1 kills the process with SIGFPE on it."""
    from beavr_sim.datasets.writer import EpisodeWriter

    video = {"dtype": "video", "shape": (32, 16, 3), "names": ["height", "width", "channels"]}
    features = {"action": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]},
                "observation.images.top": video}  # fmt: skip
    with pytest.raises(ValueError, match=r"32x16 \(HxW\) is too small .* --no-videos"):
        EpisodeWriter(tmp_path / "d", "local/d", features, 10, "xarm7_leap_right")
    assert not (tmp_path / "d").exists()


def _generate(out: Path, episodes: int, config: RecordingConfig, **kwargs):
    from beavr_sim.synthetic.generate import generate

    return generate(
        "PickupBox", episodes, 0, out, repo_id=REPO_ID, config=config, progress=False, **kwargs
    )


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ds") / "pickup_box"
    summary = _generate(root, 2, TINY)
    assert summary.episodes_written == 2, summary
    return root


def test_generated_dataset_loads_with_lerobot(dataset_root):
    ds = LeRobotDataset(REPO_ID, root=dataset_root, video_backend="pyav")
    assert ds.num_episodes == 2
    assert ds.fps == 30
    item = ds[10]
    assert item[STATE].shape == (23,) and item[ACTION].shape == (23,)
    assert tuple(item["observation.images.front"].shape) == (3, 48, 64)
    assert item["task"].startswith("Pick up the box")
    # The raw hand keypoints: tracked joints of the right hand, plausible positions (metres).
    keypoints = item[KEYPOINTS].numpy().reshape(26, 3)
    tracked = item[TRACKED].numpy() > 0.5
    assert tracked.sum() >= 20
    assert np.all(np.abs(keypoints[tracked]) < 3.0) and np.abs(keypoints[tracked]).max() > 0.05
    # delta_timestamps windows (an ACT-style action chunk).
    windowed = LeRobotDataset(
        REPO_ID,
        root=dataset_root,
        video_backend="pyav",
        delta_timestamps={ACTION: [i / 30 for i in range(5)]},
    )
    assert tuple(windowed[3][ACTION].shape) == (5, 23)
    log = [
        json.loads(x)
        for x in (dataset_root / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    ]
    assert [r["kept"] for r in log] == [True, True] and all(r["success"] for r in log)


def test_state_is_measured_before_the_recorded_action(dataset_root):
    """Frame t pairs the state measured before the tick with the action applied at it: reset
    the env with the episode's seed and step the recorded actions; every next state must be
    the recorded one exactly (a misaligned recorder would be one tick off)."""
    import gymnasium as gym

    ds = LeRobotDataset(REPO_ID, root=dataset_root, video_backend="pyav")
    ep = ds.hf_dataset.filter(lambda r: r["episode_index"] == 0)
    state = np.array(ep[STATE], dtype=np.float32)
    action = np.array(ep[ACTION], dtype=np.float32)
    seed = json.loads((dataset_root / "meta" / "beavr_episodes.jsonl").read_text().splitlines()[0])[
        "seed"
    ]
    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    try:
        env.reset(seed=seed)
        np.testing.assert_array_equal(env.agent_pos, state[0])
        for t in range(len(action) - 1):
            env.step(action[t])
            np.testing.assert_array_equal(env.agent_pos, state[t + 1], err_msg=f"tick {t}")
    finally:
        env.close()
    assert np.abs(np.diff(state[:, :7], axis=0)).max() > 1e-3  # the arm did move


def test_sigkill_during_an_episode_keeps_the_earlier_ones(tmp_path):
    root = tmp_path / "killed"
    cmd = [
        sys.executable,
        "-m",
        "beavr_sim.datasets",
        "generate",
        "--task",
        "PickupBox",
        "--episodes",
        "5",
        "--seed",
        "0",
        "--out",
        str(root),
        "--repo-id",
        REPO_ID,
        "--cameras",
        "none",
        "--quiet",
        "--workers",  # the serial writer: each episode durable in the dataset as it ends
        "1",
    ]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "MUJOCO_GL": "egl"},
    )
    log = root / "meta" / "beavr_episodes.jsonl"
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if log.is_file() and len(log.read_text().splitlines()) >= 2:
                break
            time.sleep(0.2)
        assert proc.poll() is None, "generation ended before it could be killed"
        time.sleep(1.5)  # into the next episode (synthesis or recording)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    saved = [json.loads(x) for x in log.read_text().splitlines()]
    ds = LeRobotDataset(REPO_ID, root=root)
    assert ds.num_episodes == len(saved) >= 2
    assert len(ds) == sum(r["frames"] for r in saved)
    last = ds[len(ds) - 1]
    assert int(last["episode_index"]) == ds.num_episodes - 1


@pytest.fixture(scope="module")
def act_checkpoint(dataset_root, tmp_path_factory) -> Path:
    """Two ACT training steps with lerobot-train on the generated dataset (CPU)."""
    train = Path(sys.executable).with_name("lerobot-train")
    if not train.exists():
        pytest.skip("lerobot-train is not installed beside this Python")
    out = tmp_path_factory.mktemp("train") / "act"
    cmd = [
        str(train),
        "--policy.type=act",
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={dataset_root}",
        "--dataset.video_backend=pyav",
        "--steps=2",
        "--batch_size=2",
        "--num_workers=0",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null",
        "--policy.chunk_size=10",
        "--policy.n_action_steps=10",
        "--wandb.enable=false",
        "--save_freq=2",
        "--log_freq=1",
        f"--output_dir={out}",
    ]
    result = subprocess.run(
        cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1"}
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "step:2" in result.stderr + result.stdout
    return out / "checkpoints" / "000002" / "pretrained_model"


def test_lerobot_train_runs_on_the_generated_dataset(act_checkpoint):
    assert (act_checkpoint / "model.safetensors").is_file()
    config = json.loads((act_checkpoint / "config.json").read_text())
    assert config["type"] == "act"
    assert config["input_features"]["observation.images.front"]["shape"] == [3, 48, 64]


def _eval(args, capsys) -> dict:
    from beavr_sim.eval.__main__ import main

    assert main(args) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_eval_runs_a_trained_policy_in_the_env(act_checkpoint, tmp_path, capsys):
    result = _eval(
        [
            "--policy",
            str(act_checkpoint),
            "--task",
            "pickup_box",
            "--episodes",
            "2",
            "--seed",
            "5",
            "--max-seconds",
            "1",
            "--quiet",
            "--videos",
            str(tmp_path / "v"),
        ],
        capsys,
    )
    assert result["task"] == "PickupBox" and result["episodes"] == 2
    assert result["successes"] == 0 and result["success_rate"] == 0.0  # two training steps
    assert result["mean_time_s"] == pytest.approx(1.0, abs=0.05)
    assert len(list((tmp_path / "v").glob("*.mp4"))) == 2
    # Why they failed: the checker's conditions at each episode's end (in 1 s, no lift).
    assert [e["seed"] for e in result["per_episode"]] == [5, 6]
    for episode in result["per_episode"]:
        assert set(episode["final"]) == {"lifted", "in_area", "on_table", "released", "at_rest"}
        assert episode["final"]["lifted"] is False and episode["success"] is False
    assert result["unmet_at_end"]["lifted"] == 2
    assert list(result["unmet_at_end"].values()) == sorted(result["unmet_at_end"].values())[::-1]


class _ConstantPolicy:
    """Always the same action: its open-loop error is known from the recordings alone."""

    def __init__(self, action: np.ndarray):
        self.action = action
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def act(self, observation: dict, task: str) -> np.ndarray:
        assert observation["agent_pos"].dtype == np.float32
        assert task.startswith("Pick up the box")
        return self.action


def test_open_loop_fit_measures_the_error_against_the_recorded_actions(dataset_root):
    from beavr_sim.datasets.writer import open_dataset
    from beavr_sim.eval.fit import open_loop_fit

    ds = open_dataset(dataset_root)
    actions = np.stack([np.asarray(ds[i]["action"], dtype=np.float64) for i in range(len(ds))])
    constant = actions.mean(axis=0) + 0.05
    policy = _ConstantPolicy(constant)
    fit = open_loop_fit(policy, ds, (0, 1))
    assert policy.resets == 2 and fit.frames == len(ds)
    err = np.abs(actions - constant)
    assert fit.mean_abs == pytest.approx(err.mean())
    names = ds.meta.features["action"]["names"]
    assert list(fit.per_dimension) == names
    assert fit.per_dimension[names[0]] == pytest.approx(err[:, 0].mean())
    moving = actions.std(axis=0) > 1e-9
    expected = np.mean(err.mean(axis=0)[moving] / actions.std(axis=0)[moving])
    assert fit.relative == pytest.approx(expected) and fit.relative > 0.5  # a constant
    with pytest.raises(ValueError, match=r"episodes \[2\] are not in the dataset"):
        open_loop_fit(policy, ds, (0, 2))


def test_a_recorded_frame_becomes_the_observation_the_env_gives():
    """Images come back from LeRobot as C x H x W floats in [0, 1]; the env gives H x W x C
    uint8 under ``pixels`` (what the policy's preprocessing expects)."""
    from beavr_sim.eval.fit import env_observation

    image = np.random.default_rng(0).integers(0, 256, size=(24, 32, 3), dtype=np.uint8)
    frame = {
        "observation.state": np.arange(3, dtype=np.float64),
        "observation.environment_state": np.ones(2),
        "observation.images.front": image.transpose(2, 0, 1).astype(np.float32) / 255.0,
        "action": np.zeros(3),
    }
    obs = env_observation(frame)
    assert obs["agent_pos"].dtype == np.float32 and obs["environment_state"].shape == (2,)
    assert obs["pixels"]["front"].dtype == np.uint8
    np.testing.assert_array_equal(obs["pixels"]["front"], image)
    assert "pixels" not in env_observation({"observation.state": np.zeros(3)})


def test_fit_cli_prints_its_json_for_a_trained_policy(act_checkpoint, dataset_root, capsys):
    from beavr_sim.eval.fit import main

    assert main(["--policy", str(act_checkpoint), "--dataset", str(dataset_root)]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out.strip().splitlines()[-1])
    assert result["episodes"] == [0] and result["frames"] > 0
    assert result["mean_abs"] > 0 and result["relative"] > 0  # two training steps
    assert "open-loop fit on" in captured.err
    assert main(["--policy", str(act_checkpoint), "--dataset", str(dataset_root / "x")]) == 2
    assert "no LeRobot dataset" in capsys.readouterr().err


def test_eval_async_think_act_reports_jitter_and_starved_ticks(act_checkpoint, capsys):
    result = _eval(
        [
            "--policy",
            str(act_checkpoint),
            "--task",
            "pickup_box",
            "--episodes",
            "1",
            "--max-seconds",
            "2",
            "--async",
            "--quiet",
        ],
        capsys,
    )
    assert result["mode"] == "async" and result["ticks"] == 60
    assert result["per_episode"][0]["final"]["lifted"] is False  # the think-act loop's end too
    # The first chunk is computed while the loop already runs: at least one tick waits.
    assert 1 <= result["ticks_without_action"] < result["ticks"]
    # Reported, not bounded: how late ticks come is the machine's (a benchmark's number).
    jitter = result["control_jitter_ms"]
    assert 0.0 <= jitter["p50"] <= jitter["p99"] <= jitter["max"] < float("inf")


def test_eval_rejects_a_folder_that_is_no_policy(tmp_path, capsys):
    from beavr_sim.eval.__main__ import main

    assert main(["--policy", str(tmp_path), "--task", "pickup_box", "--quiet"]) == 2
    assert "not a LeRobot pretrained policy" in capsys.readouterr().err


def test_teleop_record_writes_one_episode_per_trace_replay(tmp_path, capsys):
    from beavr_sim.teleop.__main__ import main

    root = tmp_path / "rec"
    code = main(
        [
            "--task",
            "pickup_box",
            "--source",
            "trace",
            "--no-viser",
            "--headless",
            "--record",
            str(root),
            "--repo-id",
            REPO_ID,
            "--episodes",
            "2",
            "--cameras",
            "none",
            "--quiet",
        ]
    )
    assert code == 0
    ds = LeRobotDataset(REPO_ID, root=root)
    assert ds.num_episodes == 2
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["success"]
    log = [json.loads(x) for x in (root / "meta" / "beavr_episodes.jsonl").read_text().splitlines()]
    assert [r["success"] for r in log] == [True, True]
    # Both replays of the same trace on the same seed recorded the same frames.
    ep = [
        np.array(ds.hf_dataset.filter(lambda r, i=i: r["episode_index"] == i)[ACTION])
        for i in (0, 1)
    ]
    np.testing.assert_array_equal(ep[0], ep[1])


def test_episodes_start_stop_and_discard_on_request(tmp_path):
    """Manual start: requests from the keyboard (a pipe here), the browser buttons and the
    headset gesture act on the episode at tick boundaries: stop saves, discard drops, quit
    saves and ends; every recorded episode begins from a fresh reset."""
    import io

    from beavr_sim.teleop.episodes import EpisodeControl, KeyboardControl
    from beavr_sim.teleop.session import (
        ProgressLine,
        SessionOptions,
        build_loop,
        record_episodes,
    )

    options = SessionOptions(
        task="PickupBox",
        source="trace",
        viser=False,
        headless=True,
        progress=False,
        record=tmp_path / "rec",
        repo_id=REPO_ID,
        episodes=10,
        recording=RecordingConfig(cameras=()),
        auto_start=False,
    )
    loop = build_loop(options)
    control = EpisodeControl()
    ticks = []

    def _read_all(keyboard: KeyboardControl) -> None:  # its line handled before the next tick
        assert keyboard.join(HANG_GUARD_S), "the keyboard thread did not finish its input"

    script = {
        3: lambda: control.request("start", "browser"),
        20: lambda: control.request("toggle", "browser"),
        40: lambda: _read_all(KeyboardControl(control, io.StringIO("\n"))),  # Enter: start
        50: lambda: control.request("discard", "browser"),
        60: lambda: control.request("toggle", "browser"),
        70: lambda: setattr(loop.operator, "_gestures", ["record"]),  # long left pinch
        75: lambda: control.request("start", "browser"),
        85: lambda: _read_all(KeyboardControl(control, io.StringIO("q\n"))),
    }

    def listener(tick):
        ticks.append(tick.state.t)
        if len(ticks) in script:
            script[len(ticks)]()

    loop.listeners.append(listener)
    record_episodes(options, loop, ProgressLine(loop, enabled=False), control)
    assert len(ticks) == 85  # quit ended the session at once
    log = [
        json.loads(x)
        for x in (tmp_path / "rec" / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    ]
    assert [r["ended_by"] for r in log] == ["toggle", "discard", "toggle", "quit"]
    assert [r["kept"] for r in log] == [True, False, True, True]
    assert [r["frames"] for r in log] == [17, 10, 10, 10]
    ds = LeRobotDataset(REPO_ID, root=tmp_path / "rec")
    assert ds.num_episodes == 3
    # What was saved is what the log says: the discarded episode's 10 frames are in no
    # episode (read back from the dataset's frames and from LeRobot's episode table).
    kept = [r for r in log if r["kept"]]
    assert [r["episode_index"] for r in kept] == [0, 1, 2]
    index = np.asarray(ds.hf_dataset["episode_index"])
    assert [int((index == i).sum()) for i in range(3)] == [r["frames"] for r in kept]
    assert [int(n) for n in ds.meta.episodes["length"]] == [r["frames"] for r in kept]
    assert len(ds) == sum(r["frames"] for r in kept)
    # Each episode starts from the reset state: its first recorded state is the home pose.
    home = loop.twin.env.joints.home
    for i in range(3):
        first = ds.hf_dataset.filter(lambda r, i=i: r["episode_index"] == i)[0]
        np.testing.assert_allclose(np.asarray(first[STATE]), home, atol=1e-5)


def test_a_kill_while_metadata_is_rewritten_leaves_the_previous_file_whole(tmp_path, monkeypatch):
    """LeRobot rewrites meta/info.json after every episode; a process killed during that write
    must leave the previous file (an in-place write leaves it empty or cut, and the dataset
    unreadable)."""
    from lerobot.datasets import io_utils

    from beavr_sim.datasets.writer import require_lerobot

    require_lerobot()  # what every writer does first
    info = tmp_path / "meta" / "info.json"
    io_utils.write_info(type("Info", (), {"to_dict": lambda self: {"total_episodes": 2}})(),
                        tmp_path)  # fmt: skip

    def killed_midway(data, f, **kwargs):
        f.write('{"total_episo')
        raise KeyboardInterrupt  # the kill, halfway through the bytes

    with monkeypatch.context() as m:
        m.setattr(json, "dump", killed_midway)
        with pytest.raises(KeyboardInterrupt):
            io_utils.write_info(
                type("Info", (), {"to_dict": lambda self: {"total_episodes": 3}})(), tmp_path
            )
    assert json.loads(info.read_text()) == {"total_episodes": 2}
    assert [p.name for p in info.parent.iterdir()] == ["info.json"]  # no temporary left
