"""Demonstrations multiplied (``datasets augment``): the segmenter on a recorded source, new
episodes at new seeds that succeed and replay open loop, and the object transform as the
thing that makes them succeed."""

from __future__ import annotations

import json
import shutil
from itertools import pairwise
from pathlib import Path

import mujoco
import numpy as np
import pytest

from beavr_sim.datasets.features import RecordingConfig
from beavr_sim.datasets.shards import read_log

pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")

from beavr_sim.datasets.augment import execute as execute_module
from beavr_sim.datasets.augment.execute import ExecuteConfig, Rig, execute
from beavr_sim.datasets.augment.frames import FULL_TURN, body_yaw_symmetry, carry
from beavr_sim.datasets.augment.replay import replay
from beavr_sim.datasets.augment.segments import find_segments
from beavr_sim.datasets.augment.source import load_episode, open_source

NEW_SEEDS = (100, 101)


@pytest.fixture(scope="module")
def source_root(tmp_path_factory) -> Path:
    """One PickPlace episode recorded by ``datasets generate`` (no cameras)."""
    from beavr_sim.synthetic.generate import generate

    root = tmp_path_factory.mktemp("augment") / "source"
    summary = generate("PickPlace", 1, 0, root, config=RecordingConfig(cameras=()), progress=False)
    assert summary.episodes_written == 1, summary
    return root


@pytest.fixture(scope="module")
def plan(source_root):
    source = open_source(source_root)
    traj = replay(load_episode(source, source.episodes[0]))
    return source, traj, find_segments(traj)


def test_symmetry_and_carry():
    spec = mujoco.MjSpec()
    body = spec.worldbody.add_body(name="b")
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.03, 0.04, 0])
    square = spec.worldbody.add_body(name="s")
    square.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.02])
    two = spec.worldbody.add_body(name="t")
    two.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.02])
    two.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.02], pos=[0.1, 0, 0])
    model = spec.compile()
    geoms = [np.flatnonzero(model.geom_bodyid == model.body(n).id) for n in "bst"]
    assert [body_yaw_symmetry(model, g) for g in geoms] == [0.0, np.pi / 2, FULL_TURN]
    # A square turned by 80 degrees is the square turned by -10: the palm turns -10.
    T = carry(np.zeros(3), 0.0, np.array([0.1, 0.2, 0.0]), np.deg2rad(80), np.pi / 2)
    assert np.isclose(np.arctan2(T[1, 0], T[0, 0]), np.deg2rad(-10))
    assert np.allclose(T[:3, 3], [0.1, 0.2, 0.0])


def test_source_without_episode_log_is_refused(tmp_path):
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "info.json").write_text("{}")
    with pytest.raises(ValueError, match=r"beavr_episodes\.jsonl"):
        open_source(tmp_path)


def test_a_source_without_environment_state_has_its_seed_found_by_replay(source_root, tmp_path):
    """No episode log and no ``observation.environment_state`` (the default recording): the
    seed is the candidate whose reset, with the recorded actions replayed, gives back the
    recorded ``observation.state``; with the true seed not among the candidates, refused in
    one line that says what is missing and how to record it."""
    from beavr_sim.datasets.augment.recover import RecoveryConfig, recover
    from beavr_sim.datasets.features import ENV_STATE
    from beavr_sim.datasets.shards import EPISODE_LOG

    (seed,) = open_source(source_root).seeds
    edited = tmp_path / "edited"
    shutil.copytree(source_root, edited)
    (edited / EPISODE_LOG).unlink()
    info = json.loads((edited / "meta" / "info.json").read_text())
    assert ENV_STATE not in info["features"]
    found = recover(edited, info, RecoveryConfig(seeds=range(seed, seed + 50)))
    assert (found.task, found.embodiment) == ("PickPlace", "xarm7_leap_right")
    assert found.seeds == {0: seed}
    with pytest.raises(ValueError) as refused:
        recover(edited, info, RecoveryConfig(seeds=range(seed + 1, seed + 4)))
    message = str(refused.value)
    assert "\n" not in message
    assert f"no reset at seeds {seed + 1}..{seed + 3} reproduces its observation.state" in message
    assert "--environment-state" in message and str(EPISODE_LOG) in message


def test_augment_cli_says_what_is_wrong_in_one_line(tmp_path, capsys):
    from beavr_sim.datasets.__main__ import main

    code = main(["augment", "--source", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"error: no LeRobot dataset in {tmp_path / 'nothing'} (meta/info.json is missing)"
    ]


def test_segmenter_finds_approach_grasp_transport_release(plan):
    _, traj, segments = plan
    assert traj.success  # the source replays to success from its seed
    assert [(s.kind, s.object, s.reference) for s in segments] == [
        ("approach", "item", "item"),
        ("grasp", "item", "item"),
        ("transport", "item", "target"),
        ("release", "item", "target"),
    ]
    assert segments[0].start == 0 and segments[-1].stop == traj.frames
    assert all(a.stop == b.start for a, b in pairwise(segments))


def test_augmented_episodes_succeed_in_moved_scenes_and_replay(
    source_root, plan, tmp_path, monkeypatch
):
    from beavr_sim.synthetic.generate import generate

    # Only the source drives the new episodes: with no scripted expert for any task, they are
    # made all the same (a user's new task has none).
    monkeypatch.setattr("beavr_sim.experts.registry.EXPERTS", {})
    source, traj, _ = plan
    out = tmp_path / "augmented"
    summary = generate(
        source.task, len(NEW_SEEDS), NEW_SEEDS[0], out, embodiment=source.embodiment,
        config=source.recording_config(), progress=False, source=source_root,
    )  # fmt: skip
    assert summary.episodes_written >= 1, summary
    assert sum(summary.failure_reasons.values()) == summary.failures
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["features"].keys() == source.features.keys()
    result = open_source(out)
    assert set(result.seeds) <= set(range(NEW_SEEDS[0], NEW_SEEDS[0] + 20))
    records = [r for r in read_log(out) if r["kept"]]
    assert len(records) == summary.episodes_written
    for record in records:
        assert record["source_episode"] == source.episodes[0]
        assert record["source_seed"] == traj.episode.seed
    for index in result.episodes:
        new = replay(load_episode(result, index))  # open loop, from the recorded seed
        assert new.success, f"episode {index} does not replay to success"
        moved = np.linalg.norm(new.start_pos["item"][:2] - traj.start_pos["item"][:2])
        assert moved > 0.01, "the new scene's item stands where the source's did"
    again = generate(
        source.task, len(NEW_SEEDS), NEW_SEEDS[0], out, embodiment=source.embodiment,
        config=source.recording_config(), progress=False, source=source_root,
    )  # fmt: skip
    assert again.mode == "resume" and again.episodes_written == 0
    assert sorted(again.seeds_skipped) == sorted(result.seeds)


def test_without_the_object_transform_the_new_scenes_fail(plan, monkeypatch):
    _, traj, segments = plan
    rig = Rig(traj.episode.task, traj.episode.embodiment)
    config = ExecuteConfig(tail_seconds=0.0)

    def run() -> list[bool]:
        results = []
        for seed in NEW_SEEDS:
            rig.reset(seed)
            results.append(execute(rig, traj, segments, seed, config).success)
        return results

    assert any(run())
    monkeypatch.setattr(execute_module, "carry", lambda *args: np.eye(4))
    assert not any(run())


def test_a_source_edited_with_lerobots_tools_keeps_its_seeds(tmp_path):
    """``lerobot-edit-dataset --operation.type delete_episodes`` (its function, in process) on
    a 2-episode source drops the episode log; the kept episode's task, embodiment and seed are
    recovered from what LeRobot carried (task string, robot_type, first environment state)."""
    from lerobot.datasets.dataset_tools import delete_episodes
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from beavr_sim.datasets.augment.replay import hand_body, hand_pose
    from beavr_sim.datasets.features import lerobot_features
    from beavr_sim.datasets.recorder import EpisodeRecorder
    from beavr_sim.datasets.shards import EPISODE_LOG
    from beavr_sim.datasets.writer import EpisodeWriter
    from beavr_sim.wire.records import Tick

    rig = Rig("PickPlace", "xarm7_leap_right")
    env, (arm,) = rig.env, rig.arms
    config = RecordingConfig(cameras=(), environment_state=True, tail_seconds=0.0)
    features = lerobot_features(env.embodiment, config, env.environment_state_names)
    root = tmp_path / "two"
    writer = EpisodeWriter(root, "beavr_sim/two", features, config.fps, env.embodiment.name,
                           use_videos=False)  # fmt: skip
    recorder = EpisodeRecorder(writer, env, config)
    for seed in (3, 7):  # a few ticks holding still at each seed's reset
        rig.reset(seed)
        target = {arm: hand_pose(env, hand_body(env, arm))}
        fingers = {arm: rig.twin.action[rig.slice[arm]][rig.ik[arm].n_arm :].copy()}
        recorder.begin()
        for _ in range(3):
            commands, state = rig.tick(target, fingers)
            recorder(Tick(state.t, (), commands, state))
        assert recorder.end(keep=True, success=False, seed=seed)
    recorder.close()
    assert open_source(root).seeds == (3, 7)

    edited = tmp_path / "edited"
    delete_episodes(LeRobotDataset("beavr_sim/two", root=root), [0], output_dir=edited,
                    repo_id="beavr_sim/edited")  # fmt: skip
    assert not (edited / EPISODE_LOG).exists()  # LeRobot's tool dropped it
    source = open_source(edited)
    assert (source.task, source.embodiment) == ("PickPlace", "xarm7_leap_right")
    assert (source.episodes, source.seeds) == ((0,), (7,))
    assert load_episode(source, 0).actions.shape == (3, len(rig.twin.action))
