"""Re-running ``python -m beavr_sim.datasets generate`` into the same ``--out``: it resumes
(seeds already in the dataset are not recorded again) or, with ``--overwrite``, starts anew,
and says which on stderr; serially and with worker processes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")

from beavr_sim.datasets.__main__ import main
from beavr_sim.datasets.shards import read_log

TINY = ["--cameras", "front", "--image-size", "24x32", "--no-keypoints", "--quiet"]


def _run(capsys, out: Path, *args: str) -> tuple[dict, str]:
    argv = ["generate", "--task", "pickup_box", "--seed", "0", "--out", str(out), *TINY, *args]
    assert main(argv) == 0
    captured = capsys.readouterr()
    return json.loads(captured.out.strip().splitlines()[-1]), captured.err


def _seeds(out: Path) -> list[int]:
    return [r["seed"] for r in read_log(out) if r["kept"]]


def _episodes(out: Path) -> int:
    return json.loads((out / "meta" / "info.json").read_text())["total_episodes"]


def test_a_rerun_resumes_skipping_seeds_already_there_serial_and_parallel(tmp_path, capsys):
    out = tmp_path / "ds"
    summary, err = _run(capsys, out, "--episodes", "1", "--workers", "1")
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


def test_overwrite_starts_anew_and_says_so(tmp_path, capsys):
    out = tmp_path / "ds"
    _run(capsys, out, "--episodes", "1", "--workers", "1")
    summary, err = _run(capsys, out, "--episodes", "1", "--workers", "1", "--overwrite")
    assert summary["mode"] == "overwrite" and "overwriting" in err and "1 episodes" in err
    assert summary["episodes_written"] == 1 and summary["seeds_skipped"] == []
    assert _seeds(out) == [0] and _episodes(out) == 1
