"""Re-running ``python -m beavr_sim.datasets generate`` into the same ``--out``: it resumes
(seeds already in the dataset are not recorded again) or, with ``--overwrite``, starts anew,
and says which on stderr; serially and with worker processes."""

from __future__ import annotations

import io
import json
import shutil
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")

from beavr_sim.datasets.__main__ import main
from beavr_sim.datasets.shards import read_log

TINY = ["--cameras", "front", "--image-size", "24x32", "--no-keypoints", "--quiet"]


def _argv(out: Path, *args: str) -> list[str]:
    return ["generate", "--task", "pickup_box", "--seed", "0", "--out", str(out), *TINY, *args]


def _run(capsys, out: Path, *args: str) -> tuple[dict, str]:
    assert main(_argv(out, *args)) == 0
    captured = capsys.readouterr()
    return json.loads(captured.out.strip().splitlines()[-1]), captured.err


@pytest.fixture(scope="module")
def first_run(tmp_path_factory) -> tuple[Path, dict, str]:
    """The command every test starts with, run once: one episode (seed 0) into a new dataset on
    one worker. (dataset, its summary, its stderr); a test copies the dataset before using it."""
    out = tmp_path_factory.mktemp("first") / "ds"
    stdout, stderr = io.StringIO(), io.StringIO()
    with redirect_stdout(stdout), redirect_stderr(stderr):
        assert main(_argv(out, "--episodes", "1", "--workers", "1")) == 0
    return out, json.loads(stdout.getvalue().strip().splitlines()[-1]), stderr.getvalue()


def _copy(first_run: tuple[Path, dict, str], tmp_path: Path) -> Path:
    out = tmp_path / "ds"
    shutil.copytree(first_run[0], out)
    return out


def _seeds(out: Path) -> list[int]:
    return [r["seed"] for r in read_log(out) if r["kept"]]


def _episodes(out: Path) -> int:
    return json.loads((out / "meta" / "info.json").read_text())["total_episodes"]


def test_a_rerun_resumes_skipping_seeds_already_there_serial_and_parallel(
    first_run, tmp_path, capsys
):
    out = _copy(first_run, tmp_path)
    _, summary, err = first_run
    assert summary["mode"] == "new" and "new dataset" in err
    assert _seeds(out) == [0]

    # The same command again: seed 0 is there, nothing is recorded twice.
    summary, err = _run(capsys, out, "--episodes", "1", "--workers", "1")
    assert summary["mode"] == "resume" and summary["seeds_skipped"] == [0], summary
    assert summary["episodes_written"] == 0 and "resuming" in err and "--overwrite" in err
    assert _seeds(out) == [0] and _episodes(out) == 1

    # More episodes through workers: seed 0 skipped, seed 1 recorded, each once.
    summary, err = _run(capsys, out, "--episodes", "2", "--workers", "2")
    assert summary["mode"] == "resume" and summary["seeds_skipped"] == [0], summary
    assert summary["episodes_written"] == 1 and summary["backend"] == "local"
    assert _seeds(out) == [0, 1] and _episodes(out) == 2
    assert [r["episode_index"] for r in read_log(out)] == [0, 1]

    # Parallel re-run with everything there: nothing to do.
    summary, _ = _run(capsys, out, "--episodes", "2", "--workers", "2")
    assert summary["seeds_skipped"] == [0, 1] and summary["episodes_written"] == 0
    assert _seeds(out) == [0, 1] and _episodes(out) == 2


def test_overwrite_starts_anew_and_says_so(first_run, tmp_path, capsys):
    out = _copy(first_run, tmp_path)
    summary, err = _run(capsys, out, "--episodes", "1", "--workers", "1", "--overwrite")
    assert summary["mode"] == "overwrite" and "overwriting" in err and "1 episodes" in err
    assert summary["episodes_written"] == 1 and summary["seeds_skipped"] == []
    assert _seeds(out) == [0] and _episodes(out) == 1
