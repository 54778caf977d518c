"""``python -m beavr_sim.hardware.guard``: one JSON verdict per row, alone or as a stream."""

from __future__ import annotations

import json

import numpy as np

from beavr_sim.hardware.guard import main, scene_guard


def _run(capsys, *argv) -> tuple[int, list[dict]]:
    code = main(list(argv))
    lines = capsys.readouterr().out.strip().splitlines()
    return code, [json.loads(line) for line in lines]


def test_rows_alone_and_as_a_stream(tmp_path, capsys):
    _, _, home = scene_guard("xarm7_leap_right")
    rows = np.stack([home, home, home, home])
    rows[1, 2] = np.nan
    rows[2, 3] = 9.0
    rows[3, 0] += 0.5  # fine alone, a 15 rad/s jump as a 30 Hz stream
    path = tmp_path / "rows.npy"
    np.save(path, rows)
    code, out = _run(capsys, "--qpos-file", str(path))
    assert code == 1
    assert [r["ok"] for r in out] == [True, False, False, True]
    assert out[1]["reason"] == "right: non-finite: right/joint3 = nan"
    assert out[2]["reason"].startswith("right: joint limit: right/joint4 = 9.0000 >")
    code, out = _run(capsys, "--qpos-file", str(path), "--stream", "--hz", "30")
    assert [r["ok"] for r in out] == [True, False, False, False]
    assert out[3]["reason"].startswith("right: velocity: right/joint1 15")
    # The same jump at 1 Hz is slow enough.
    code, out = _run(capsys, "--qpos-file", str(path), "--stream", "--hz", "1")
    assert out[3]["ok"]


def test_descent_stream_is_refused_at_the_table(tmp_path, capsys):
    _, _, home = scene_guard("xarm7_leap_right")
    goal = home.copy()
    goal[0], goal[1], goal[3] = 0.5, 1.45, 1.2
    rows = np.array([home + (goal - home) * k / 300 for k in range(1, 301)])
    np.save(tmp_path / "descent.npy", rows)
    code, out = _run(capsys, "--qpos-file", str(tmp_path / "descent.npy"), "--stream")
    first = next(r for r in out if not r["ok"])
    assert code == 1 and first["reason"].startswith("right: workspace: right/")
    assert "below the box (z" in first["reason"]
    assert all(not r["ok"] for r in out[first["row"] :])


def test_bad_input_is_a_clear_error(tmp_path, capsys):
    np.save(tmp_path / "short.npy", np.zeros((2, 5)))
    assert main(["--qpos-file", str(tmp_path / "short.npy")]) == 2
    assert "expected an (N, 23) array" in capsys.readouterr().err
    assert main(["--qpos-file", str(tmp_path / "missing.npy")]) == 2
    assert main(["--qpos-file", str(tmp_path / "short.npy"), "--embodiment", "rx2"]) == 2
    assert "Valid" in capsys.readouterr().err
