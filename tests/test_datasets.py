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


def _generate(out: Path, episodes: int, config: RecordingConfig, **kwargs):
    from beavr_sim.datasets.generate import generate

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


def test_state_follows_the_recorded_action(dataset_root):
    """observation.state[t] is measured before action[t] is applied: the arm moves towards the
    commanded targets (a position servo), so the next state is closer to the action."""
    ds = LeRobotDataset(REPO_ID, root=dataset_root, video_backend="pyav")
    ep = ds.hf_dataset.filter(lambda r: r["episode_index"] == 0)
    state = np.array(ep[STATE])
    action = np.array(ep[ACTION])
    arm = slice(0, 7)
    moving = np.linalg.norm(action[:-1, arm] - state[:-1, arm], axis=1) > 1e-3
    before = np.linalg.norm(action[:-1, arm] - state[:-1, arm], axis=1)[moving]
    after = np.linalg.norm(action[:-1, arm] - state[1:, arm], axis=1)[moving]
    assert moving.sum() > 20
    assert np.mean(after < before) > 0.9


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


def test_lerobot_train_runs_on_the_generated_dataset(dataset_root, tmp_path):
    train = Path(sys.executable).with_name("lerobot-train")
    if not train.exists():
        pytest.skip("lerobot-train is not installed beside this Python")
    out = tmp_path / "train"
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
        "--wandb.enable=false",
        "--save_freq=2",
        "--log_freq=1",
        f"--output_dir={out}",
    ]
    result = subprocess.run(
        cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1"}
    )
    assert result.returncode == 0, result.stderr[-3000:]
    model = out / "checkpoints" / "000002" / "pretrained_model"
    assert (model / "model.safetensors").is_file() and (model / "config.json").is_file()
    assert "step:2" in result.stderr + result.stdout
