"""A robot file's name outside the process (beavr_sim.robots.identity, datasets.robot_meta):
datasets, eval summaries and the experts see the file's ``name``; a dataset records the file's
path and hash and is found again by them, or refused in one line when the file is gone or
changed. And every command's ``--embodiment`` takes a robot file (demo) or refuses it in one
line where it cannot use one (the scripted experts)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_robot_file import xarm_toml

from beavr_sim.datasets.augment.source import open_source
from beavr_sim.datasets.robot_meta import ROBOT_META, dataset_embodiment
from beavr_sim.datasets.shards import EPISODE_LOG
from beavr_sim.datasets.writer import EpisodeWriter
from beavr_sim.eval.runner import EpisodeResult, summarize
from beavr_sim.robots.identity import file_sha256, robot_identity


@pytest.fixture
def robot(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = tmp_path / "robots" / "mine.toml"
    path.parent.mkdir()
    path.write_text(xarm_toml())  # name = "xarm_from_file"
    return path


def test_a_robot_file_is_named_by_its_name_with_its_path_and_hash(robot):
    assert robot_identity("xarm7_leap_right").as_dict() == {
        "name": "xarm7_leap_right", "path": "", "sha256": ""
    }  # fmt: skip
    identity = robot_identity(str(robot))
    assert (identity.name, identity.path) == ("xarm_from_file", str(robot.resolve()))
    assert identity.sha256 == file_sha256(robot) and len(identity.sha256) == 64


def test_a_dataset_of_a_robot_file_names_it_and_finds_it_again(robot, tmp_path):
    root = tmp_path / "data"
    features = {"action": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}}
    writer = EpisodeWriter(root, "local/data", features, 10, str(robot), use_videos=False)
    for _ in range(2):
        writer.add_frame({"action": np.zeros(2, np.float32)}, task="PickupBox")
    assert writer.save_episode()
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["robot_type"] == "xarm_from_file"  # not the file's path
    assert json.loads((root / ROBOT_META).read_text())["path"] == str(robot.resolve())
    record = {"episode_index": 0, "kept": True, "seed": 3, "task": "PickupBox",
              "embodiment": "xarm_from_file"}  # fmt: skip
    (root / EPISODE_LOG).write_text(json.dumps(record) + "\n")
    assert open_source(root).embodiment == str(robot.resolve())  # augment loads the file
    assert dataset_embodiment(root, "xarm7_leap_right") == "xarm7_leap_right"

    robot.write_text(robot.read_text() + "\n# edited\n")
    with pytest.raises(ValueError, match=r"mine\.toml \(name 'xarm_from_file', sha256 .*changed"):
        open_source(root)
    robot.unlink()
    with pytest.raises(FileNotFoundError, match=r"mine\.toml \(name 'xarm_from_file'\), which no"):
        open_source(root)
    (root / ROBOT_META).unlink()
    with pytest.raises(ValueError, match=r"not a built-in .* no meta/beavr_robot\.json"):
        dataset_embodiment(root, "xarm_from_file")


def test_an_eval_summary_names_a_robot_file_by_its_name_and_file(robot):
    results = [EpisodeResult(seed=0, success=True, seconds=1.0, ticks=30)]
    summary = summarize(results, "PickupBox", str(robot), "act", False, 30.0)
    assert summary["embodiment"] == "xarm_from_file"
    assert summary["robot_file"]["path"] == str(robot.resolve())
    assert "robot_file" not in summarize(
        results, "PickupBox", "xarm7_leap_right", "act", False, 30.0
    )


def test_the_demo_takes_a_robot_file_and_refuses_a_missing_one_in_one_line(robot, capsys):
    from beavr_sim.demo import main

    with pytest.raises(SystemExit) as exit_:
        main(["--embodiment", str(robot.with_name("gone.toml")), "--no-viser"])
    assert exit_.value.code == 2
    assert "error: robot file" in capsys.readouterr().err
    assert main(["--embodiment", str(robot), "--no-viser", "--seconds", "0.05"]) == 0


def test_the_scripted_experts_refuse_a_robot_file_naming_the_built_ins(robot, capsys):
    from beavr_sim.experts.__main__ import main

    assert main(["--task", "PickupBox", "--embodiment", str(robot), "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "run on the built-in embodiments (xarm7_leap_right," in err and "mine.toml" in err
