"""Scaling out (issue 23): executors with retries, parallel generation merged with LeRobot's
``aggregate_datasets`` (identical to a serial run of the same seeds, also when a worker dies
mid-episode), the same on a local Ray cluster, and evaluation sweeps with Wilson intervals."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from beavr_sim.datasets.features import RecordingConfig
from beavr_sim.scaling.executors import (
    JobFailed,
    LocalPool,
    ScaleConfig,
    make_executor,
    require_ray,
)
from beavr_sim.scaling.stats import wilson_interval

lerobot = pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

REPO_ID = "test/scaling"
#: Tiny images and one second of recording per episode (kept though it did not succeed yet):
#: the synthesis still runs the expert's whole episode.
TINY = RecordingConfig(cameras=("front",), image_height=24, image_width=32, episode_seconds=1.0)
EPISODES = 2


# ---------------------------------------------------------------------------- small parts
def test_wilson_interval_matches_known_values():
    low, high = wilson_interval(5, 10)
    assert (round(low, 4), round(high, 4)) == (0.2366, 0.7634)
    assert wilson_interval(0, 2) == (0.0, pytest.approx(0.6576, abs=1e-4))
    low, high = wilson_interval(20, 20)
    assert high == 1.0 and low == pytest.approx(0.8389, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(3, 2)


def test_scale_config_is_validated():
    with pytest.raises(ValueError, match="workers"):
        ScaleConfig(workers=0)
    with pytest.raises(ValueError, match="max_attempts"):
        ScaleConfig(max_attempts=0)
    with pytest.raises(ValueError, match="--ray"):
        ScaleConfig(ray_address="auto")
    assert ScaleConfig(workers=1).in_process and ScaleConfig().local_workers == os.cpu_count()
    assert ScaleConfig(workers=2).backend == "local" and ScaleConfig(ray=True).backend == "ray"


def test_local_pool_retries_a_dead_worker_then_gives_up():
    # Jobs are stdlib functions: math.sqrt answers, os._exit kills its worker every time.
    pool = LocalPool("math:sqrt", workers=2, max_attempts=2)
    try:
        for i, x in enumerate([4.0, 9.0, 16.0]):
            pool.submit(i, x)
        results = dict(pool.next_result() for _ in range(3))
        assert results == {0: 2.0, 1: 3.0, 2: 4.0}
        pool.submit("bad", -1.0)  # raises ValueError in the worker: retried, then fails
        with pytest.raises(JobFailed, match="math domain error"):
            pool.next_result()
    finally:
        pool.close()
    dying = LocalPool("os:_exit", workers=1, max_attempts=2)
    try:
        dying.submit("exit", 3)
        with pytest.raises(JobFailed, match="exit code 3"):
            dying.next_result()
        assert dying.stats.died == 2 and dying.retried == 1
    finally:
        dying.close()


def test_local_pool_retires_idle_workers_and_still_runs_later_jobs():
    pool = LocalPool("math:sqrt", workers=2)
    try:
        pool.submit(0, 4.0)
        pool.submit(1, 9.0)
        first = dict([pool.next_result()])
        # One job is left: the worker that finished exits now, the busy one is kept.
        assert pool.retire_idle() == 1
        assert pool.retire_idle() == 0  # (already gone)
        second = dict([pool.next_result()])
        assert {**first, **second} == {0: 2.0, 1: 3.0}
        assert pool.retire_idle() == 1
        pool.submit(2, 16.0)  # work after all: a fresh worker takes it
        assert pool.next_result() == (2, 4.0) and pool.stats.started == 3
        assert pool.stats.died == 0  # retiring is not dying
    finally:
        pool.close()
    assert pool.pending == 0


def test_ray_missing_gives_install_instructions(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ImportError, match=r"pip install -e '\.\[scale\]'"):
        require_ray()
    with pytest.raises(ImportError, match="optional extra"):
        make_executor("math:sqrt", ScaleConfig(ray=True))


# ---------------------------------------------------------------------------- generation
def _generate(out: Path, scale: ScaleConfig | None):
    from beavr_sim.synthetic.generate import generate

    return generate(
        "PickupBox",
        EPISODES,
        0,
        out,
        repo_id=REPO_ID,
        config=TINY,
        keep_failed=True,
        progress=False,
        scale=scale,
    )


@pytest.fixture(scope="module")
def serial_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("serial") / "ds"
    summary = _generate(root, None)
    assert summary.episodes_written == EPISODES and summary.backend == "inline", summary
    return root


def _log(root: Path) -> list[dict]:
    return [
        json.loads(x) for x in (root / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    ]


def assert_same_dataset(serial: Path, merged: Path) -> None:
    """Same episodes in the same order: every column, decoded images, episode log, stats."""
    a = LeRobotDataset(REPO_ID, root=serial, video_backend="pyav")
    b = LeRobotDataset(REPO_ID, root=merged, video_backend="pyav")
    assert (b.num_episodes, len(b)) == (a.num_episodes, len(a))
    assert a.meta.features.keys() == b.meta.features.keys()
    for column in a.hf_dataset.column_names:
        np.testing.assert_array_equal(
            np.array(b.hf_dataset[column]), np.array(a.hf_dataset[column]), err_msg=column
        )
    for i in (0, len(a) // 2, len(a) - 1):  # across the episodes' video files
        for key in a.meta.video_keys:
            np.testing.assert_array_equal(b[i][key].numpy(), a[i][key].numpy(), err_msg=key)
    assert _log(merged) == _log(serial)
    assert sorted(p.name for p in (merged / "beavr_traces").iterdir()) == sorted(
        p.name for p in (serial / "beavr_traces").iterdir()
    )
    for feature, stats in a.meta.stats.items():
        for name, value in stats.items():
            np.testing.assert_allclose(
                b.meta.stats[feature][name], value, rtol=1e-6, atol=1e-9, err_msg=feature + name
            )


def test_two_local_workers_with_a_worker_killed_mid_episode_equal_the_serial_run(
    serial_root, tmp_path, monkeypatch
):
    from beavr_sim.synthetic.generate import CRASH_ONCE_ENV, staging_dir

    marker = tmp_path / "crashed"
    monkeypatch.setenv(CRASH_ONCE_ENV, f"1:{marker}")  # seed 1's worker dies on attempt one
    out = tmp_path / "ds"
    summary = _generate(out, ScaleConfig(workers=2))
    assert marker.exists(), "the crash hook did not fire"
    assert summary.backend == "local" and summary.workers == 2
    assert summary.retried == 1 and summary.episodes_written == EPISODES
    assert not staging_dir(out).exists()
    assert_same_dataset(serial_root, out)


def test_ray_local_cluster_with_a_worker_killed_mid_episode_equals_the_serial_run(
    serial_root, tmp_path, monkeypatch
):
    pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[scale]')")
    from beavr_sim.synthetic.generate import CRASH_ONCE_ENV

    marker = tmp_path / "crashed"
    monkeypatch.setenv(CRASH_ONCE_ENV, f"0:{marker}")
    out = tmp_path / "ds"
    summary = _generate(out, ScaleConfig(workers=2, ray=True))
    assert marker.exists(), "the crash hook did not fire"
    assert summary.backend == "ray" and summary.episodes_written == EPISODES
    assert_same_dataset(serial_root, out)


def test_merge_appends_to_an_existing_dataset(serial_root, tmp_path):
    """Shards merged into an existing dataset come after its episodes, renumbered."""
    from beavr_sim.datasets.shards import Shard, merge_shards

    out = tmp_path / "ds"
    shutil.copytree(serial_root, out)
    shard = Shard(tmp_path / "shard")
    shutil.copytree(serial_root, shard.dataset)  # a shard of two episodes
    shutil.copytree(serial_root / "beavr_traces", shard.root / "beavr_traces")
    assert merge_shards([shard], out, REPO_ID) == 2 * EPISODES
    ds = LeRobotDataset(REPO_ID, root=out, video_backend="pyav")
    serial = LeRobotDataset(REPO_ID, root=serial_root, video_backend="pyav")
    assert ds.num_episodes == 2 * EPISODES and len(ds) == 2 * len(serial)
    assert [r["episode_index"] for r in _log(out)] == list(range(2 * EPISODES))
    assert [r["seed"] for r in _log(out)] == [0, 1, 0, 1]
    for column in ("action", "observation.state"):
        np.testing.assert_array_equal(
            np.array(ds.hf_dataset[column][len(serial) :]), np.array(serial.hf_dataset[column])
        )
    assert np.asarray(ds.meta.stats["episode_index"]["max"]).tolist() == [2 * EPISODES - 1]
    np.testing.assert_array_equal(ds[len(ds) - 1]["observation.images.front"].numpy(),
                                  serial[len(serial) - 1]["observation.images.front"].numpy())  # fmt: skip


def test_a_merge_killed_between_its_renames_is_finished_by_the_next_run(
    serial_root, tmp_path, monkeypatch
):
    """The appending merge moves the old dataset aside, then the merged one into place; a
    kill between the two leaves no dataset at ``out``. The next run puts the merged one there
    (it was whole before the first rename) and drops the old copy."""
    from beavr_sim.datasets.shards import Shard, finish_interrupted_swap, merge_shards

    out = tmp_path / "ds"
    shutil.copytree(serial_root, out)
    shard = Shard(tmp_path / "shard")
    shutil.copytree(serial_root, shard.dataset)
    rename = Path.rename

    def killed_before_the_second(self, target):
        if self.name.endswith(".merging"):
            raise SystemExit("killed")
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", killed_before_the_second)
    with pytest.raises(SystemExit):
        merge_shards([shard], out, REPO_ID)
    monkeypatch.setattr(Path, "rename", rename)
    assert not out.exists() and (tmp_path / "ds.replaced").is_dir()

    assert finish_interrupted_swap(out)
    assert not (tmp_path / "ds.replaced").exists() and not (tmp_path / "ds.merging").exists()
    assert LeRobotDataset(REPO_ID, root=out, video_backend="pyav").num_episodes == 2 * EPISODES
    assert [r["episode_index"] for r in _log(out)] == list(range(2 * EPISODES))
    assert not finish_interrupted_swap(out)  # nothing left to finish


def test_a_restarted_run_resumes_only_finished_shards_of_the_same_job(tmp_path):
    from beavr_sim.synthetic.generate import EpisodeOutcome, _resume

    manifest = {"task": "PickupBox", "config": {"cameras": ["front"]}}
    staging = tmp_path / "ds.shards"
    for seed, finished in ((0, True), (1, False), (2, True)):
        (staging / f"seed{seed:06d}").mkdir(parents=True)
        if finished:
            outcome = EpisodeOutcome(seed, seed == 0, seed == 0, 30 * (seed == 0))
            (staging / f"seed{seed:06d}" / "outcome.json").write_text(json.dumps(outcome.__dict__))
    (staging / "job.json").write_text(json.dumps(manifest))
    resumed = _resume(staging, manifest)
    assert sorted(resumed) == [0, 2] and resumed[0].written and not resumed[2].synth_ok
    assert _resume(staging, {**manifest, "task": "Pour"}) == {}  # another job: a clean slate
    assert not staging.exists()


# ---------------------------------------------------------------------------- evaluation
@pytest.fixture(scope="module")
def tiny_policy(tmp_path_factory, save_tiny_act_policy) -> Path:
    """An untrained, tiny ACT policy on the front camera (24x32): runs on every task."""
    return save_tiny_act_policy(tmp_path_factory.mktemp("policy") / "act")


def test_eval_sweep_on_two_workers_gives_one_table(tiny_policy, tmp_path, capsys):
    from beavr_sim.eval.__main__ import main

    second = tmp_path / "act_copy"
    shutil.copytree(tiny_policy, second)
    args = ["--policy", str(tiny_policy), str(second), "--task", "pickup_box", "flip_cube"]
    args += ["--episodes", "2", "--max-seconds", "0.2", "--quiet", "--seed", "7"]
    csv_path, md_path = tmp_path / "t.csv", tmp_path / "t.md"
    assert main([*args, "--workers", "2", "--table", str(csv_path), "--table", str(md_path)]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["backend"] == "local" and result["workers"] == 2
    assert result["episodes_total"] == 8
    rows = result["results"]
    assert [(Path(r["policy_path"]).name, r["task"]) for r in rows] == [
        ("act", "PickupBox"),
        ("act", "FlipCube"),
        ("act_copy", "PickupBox"),
        ("act_copy", "FlipCube"),
    ]
    for row in rows:
        assert row["episodes"] == 2 and row["successes"] == 0  # untrained, 0.2 s episodes
        assert row["success_ci95"] == [0.0, pytest.approx(0.6576, abs=1e-4)]
        assert row["mean_time_s"] == pytest.approx(0.2, abs=0.05)
    lines = csv_path.read_text().splitlines()
    assert lines[0].startswith("policy_path,policy,task,episodes,successes,success_rate,ci95_low")
    assert len(lines) == 5
    assert md_path.read_text().count("\n") == 6 and "| FlipCube |" in md_path.read_text()
    # The same sweep in this process: the same table.
    assert main([*args, "--workers", "1"]) == 0
    inline = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert inline["backend"] == "inline"
    assert inline["results"] == rows


def test_eval_rejects_a_mismatched_table_suffix(tiny_policy, capsys):
    from beavr_sim.eval.__main__ import main

    args = ["--policy", str(tiny_policy), "--task", "pickup_box", "--table", "t.txt", "--quiet"]
    assert main(args) == 2
    assert ".csv or .md" in capsys.readouterr().err
