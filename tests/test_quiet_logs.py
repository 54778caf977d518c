"""Quiet logs: a recording writes no encoder banners or ``datasets`` progress bars, and local
workers log in the command lines' format; a local worker's job may start processes (LeRobot's
video encoding of two cameras does); a warning never glues onto teleop's progress line."""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import pytest

from beavr_sim.datasets.quiet import DATASETS_BARS_ENV, SVT_LOG_ENV
from beavr_sim.scaling.executors import LocalPool
from beavr_sim.teleop.console import CONSOLE, LineSafeHandler

ROOT = Path(__file__).resolve().parents[1]


def test_generate_writes_no_encoder_banner_or_map_bar_and_stdout_is_its_json(tmp_path):
    pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
    env = {k: v for k, v in os.environ.items() if k not in (SVT_LOG_ENV, DATASETS_BARS_ENV)}
    env.update(PYTHONPATH=str(ROOT), MUJOCO_GL="egl", HF_HUB_OFFLINE="1")
    out = tmp_path / "ds"
    done = subprocess.run(
        [
            sys.executable, "-m", "beavr_sim.datasets", "generate", "--task", "pickup_box",
            "--episodes", "1", "--out", str(out), "--cameras", "front,overhead",
            "--image-size", "24x32", "--workers", "1",
        ],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout)["episodes_written"] == 1  # the whole of stdout
    lines = done.stderr.replace("\r", "\n").splitlines()
    assert not [x for x in lines if "Svt" in x or x.startswith("Map")], lines[:20]
    assert (out / "videos").is_dir()  # the videos were encoded, only quietly


def test_local_workers_log_in_the_command_lines_format(capfd):
    pool = LocalPool("logging:warning", 1)
    try:
        pool.submit(0, "hello from a worker")
        pool.next_result()
    finally:
        pool.close()
    err = capfd.readouterr().err
    assert "[beavr-worker] WARNING root: hello from a worker" in err, err


def child_exit_code(code: int) -> int:
    """A job that starts a process of its own (as LeRobot's parallel video encoding does)."""
    child = multiprocessing.get_context("spawn").Process(target=sys.exit, args=(code,))
    child.start()
    child.join()
    return child.exitcode


def test_a_local_workers_job_may_start_processes_of_its_own():
    pool = LocalPool(f"{Path(__file__).stem}:child_exit_code", 1, max_attempts=1)
    try:
        pool.submit(0, 7)
        assert pool.next_result() == (0, 7)
    finally:
        pool.close()


def test_a_warning_starts_its_own_line_after_the_progress_line(capsys):
    log = logging.getLogger("beavr_sim.test_console")
    handler = LineSafeHandler()  # on the captured stderr
    handler.setFormatter(logging.Formatter("WARNING %(message)s"))
    log.addHandler(handler)
    try:
        CONSOLE.progress("t=   1.0 s  frames=30")
        log.warning("right hand lost")
        CONSOLE.progress("t=   2.0 s  frames=60")
        CONSOLE.end_line()
        log.warning("second")
    finally:
        log.removeHandler(handler)
    err = capsys.readouterr().err
    assert err == (
        "\rt=   1.0 s  frames=30\nWARNING right hand lost\n"
        "\rt=   2.0 s  frames=60\nWARNING second\n"
    ), repr(err)
