"""Commands that promise a JSON summary on stdout print nothing else there: the xArm SDK's
prints and logs and LeRobot's "Loading weights" go to stderr."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _python(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, env=env, cwd=ROOT, timeout=timeout
    )


def test_the_xarm_sdk_prints_and_logs_on_stderr_not_stdout():
    pytest.importorskip("xarm", reason="the xArm SDK (xarm-python-sdk) is not installed")
    script = textwrap.dedent(
        """
        import json
        import numpy as np
        from beavr_sim.hardware.xarm.config import XArmConfig
        from beavr_sim.hardware.xarm.driver import XArm7
        from beavr_sim.hardware.xarm.emulator import XArmEmulator

        with XArmEmulator() as emu:
            arm = XArm7(XArmConfig(host=emu.host, port=emu.port, connect_timeout_s=5.0))
            arm.connect()
            q = arm.read_positions()
            arm.send_positions(q + 0.001)
            arm.recover()  # motion_enable again: the SDK logs it
            arm.reconnect()
            arm.disconnect()
        print(json.dumps({"joints": len(q)}))
        """
    )
    done = _python("-c", script)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout) == {"joints": 7}, done.stdout[:500]
    assert "SDK_VERSION" in done.stderr and "motion_enable" in done.stderr  # moved, not lost


def test_eval_prints_only_its_json_summary_on_stdout(tmp_path, save_tiny_act_policy):
    pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
    policy = tmp_path / "act"
    save_tiny_act_policy(policy)
    done = _python(
        "-m", "beavr_sim.eval", "--policy", str(policy), "--task", "pickup_box",
        "--episodes", "1", "--max-seconds", "0.3", "--workers", "1", "--quiet",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads(done.stdout)  # the whole of stdout is the summary
    assert summary["episodes"] == 1, summary
    assert "Loading weights" in done.stderr
