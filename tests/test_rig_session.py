"""A recording day on the emulated rig, through the real teleop CLI (issue 38).

Every session here mirrors to ``--hardware-config emulated`` (the xArm controller, Dynamixel and
Feetech bus emulators in a child process, driven through the vendors' SDKs): several recorded
episodes, ``--repeat`` runs, the RX-1, a rig that dies mid-session. Each saved dataset is read
back: in every saved episode the measured ``observation.state`` follows ``action``.
Episodes are cut to a few seconds (``--episode-seconds``, ``--max-seconds``) to keep the
runtime modest; nothing waits a fixed time (the dead-rig test waits for the session's own
progress line before it kills the emulators).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest
from recorded_state import check_follows, read_episodes

import beavr_sim
from beavr_sim.assets import bundled_trace
from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.datasets.recorder import EpisodeRecorder
from beavr_sim.datasets.writer import EpisodeWriter
from beavr_sim.teleop.__main__ import main as teleop_main
from beavr_sim.wire.records import Tick

#: The checkout whose package these tests import (subprocesses run the same code).
REPO = Path(beavr_sim.__file__).resolve().parents[1]
#: The exit code of a session whose device failed and was not recovered (docs/hardware.md).
EXIT_DEVICE_FAILED = 4
RX1_TRACE = bundled_trace("PickupBox", "rx1")
MIRRORED = ["--mirror-hardware", "--hardware-config", "emulated", "--no-viser", "--headless"]
#: ``--max-seconds`` of the ``--repeat 3`` session: two whole PickupBox traces (9.0 s each at
#: 30 Hz) and a third run cut after about half a second.
REPEAT_SECONDS = 18.5


def _summary(capsys) -> dict:
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def _check_recording(root: Path, repo_id: str, episodes: int, summary: dict) -> None:
    """Every saved episode true, and ``episodes`` of them. On a busy machine an emulated device
    can miss a reply (an outage it recovers from): that episode must then be reported as a
    hardware fault and not saved, and the trace is played again."""
    saved = read_episodes(root, repo_id)
    assert len(saved) == episodes
    for e, (state, action, names) in saved.items():
        check_follows(state, action, names, e)
    log = [json.loads(line) for line in (root / "meta" / "beavr_episodes.jsonl").open()]
    assert [r["hardware_fault"] is None for r in log] == [r["kept"] for r in log], log
    for r in log:  # every episode reports its oldest reading's age
        assert r["max_state_age_s"] is None or r["max_state_age_s"] > 0, r
    runs = summary["per_run"]
    assert summary["runs"] == len(runs) == len(log) >= episodes
    assert [r["run"] for r in runs] == list(range(1, len(runs) + 1))
    for record in runs:
        assert record["saved"] is (record["hardware_fault"] == ""), record
        assert record["duration_s"] > 0 and record["sync_s"] >= 0
        assert "diverged" not in record["hardware_fault"], record  # a reset never latches
    assert summary["hardware_faults"] == len(runs) - episodes
    assert summary["failed_devices"] == [] and summary["stopped_early"] == ""


def test_recorded_mirrored_episodes_follow_their_commands(tmp_path, capsys):
    """Item 1: three recorded episodes on the emulated xArm7 + LEAP. Each starts from a synced
    rig, so no reset latches a divergence hold: in every saved episode the measured state
    follows the action (on the old code episodes 2 and 3 froze while the action moved)."""
    root = tmp_path / "D"
    code = teleop_main(
        ["--task", "pickup_box", "--source", "trace", *MIRRORED, "--quiet",
         "--record", str(root), "--repo-id", "test/day", "--episodes", "3",
         "--episode-seconds", "3", "--cameras", "none", "--no-keypoints"]
    )  # fmt: skip
    summary = _summary(capsys)
    assert code == 0
    _check_recording(root, "test/day", 3, summary)


def test_rx1_recorded_episodes_follow_their_commands(tmp_path, capsys):
    """The same on the RX-1 (Feetech groups for arms and body, two LEAP hands)."""
    root = tmp_path / "rx1"
    code = teleop_main(
        ["--task", "pickup_box", "--embodiment", "rx1", "--source", "trace",
         "--trace", str(RX1_TRACE), *MIRRORED, "--quiet",
         "--record", str(root), "--repo-id", "test/rx1", "--episodes", "2",
         "--episode-seconds", "3", "--cameras", "none", "--no-keypoints"]
    )  # fmt: skip
    summary = _summary(capsys)
    assert code == 0
    assert summary["embodiment"] == "rx1"
    _check_recording(root, "test/rx1", 2, summary)


def test_repeated_session_syncs_every_run_and_reports_them_all(capsys):
    """Item 2: ``--repeat 3`` mirrored, the last run cut short by ``--max-seconds``: every run
    starts synced (no hardware fault in any), and the summary has every run, not only the
    last (which alone read ``success: false``)."""
    code = teleop_main(
        ["--task", "pickup_box", "--source", "trace", *MIRRORED, "--quiet",
         "--repeat", "3", "--max-seconds", str(REPEAT_SECONDS)]
    )  # fmt: skip
    summary = _summary(capsys)
    assert code == 0
    assert summary["runs"] == 3, summary.get("per_run")
    runs = summary["per_run"]
    # No reset latches a hold (on a busy machine a device may still miss a reply: an outage,
    # recovered, reported in that run's line, and that run is then not called a success).
    assert not any("diverged" in r["hardware_fault"] for r in runs), runs
    for r in runs[:2]:
        assert r["task_success"], runs
        assert r["success"] is (r["hardware_fault"] == ""), runs
    # The last run is the cut-short one the old summary described alone.
    assert runs[-1]["duration_s"] < runs[0]["duration_s"]
    assert summary["duration_s"] == pytest.approx(runs[-1]["duration_s"], abs=1e-3)
    assert sum(r["duration_s"] for r in runs) == pytest.approx(REPEAT_SECONDS, abs=0.1)
    assert summary["failed_devices"] == []
    # The arm was written all session long (on the old code it held from the first reset).
    assert summary["hardware"]["right_arm"]["commands_sent"] >= 0.8 * REPEAT_SECONDS * 30


def test_a_dry_run_reports_no_writes(capsys):
    """Issue 39 item 8: a dry run writes nothing, so its hardware block has no write latency
    or write rate; it says it was a dry run, and the devices connected all run say so."""
    code = teleop_main(
        ["--task", "pour", "--source", "trace", *MIRRORED, "--dry-run", "--quiet",
         "--max-seconds", "1"]
    )  # fmt: skip
    summary = _summary(capsys)
    assert code == 0
    assert summary["hardware"], summary
    for name, device in summary["hardware"].items():
        assert device["dry_run"] is True, name
        assert device["commands_sent"] == 0, name
        assert "write_latency_ms" not in device and "write_rate_hz" not in device, device
        assert device["connected"] is True, name


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(p) for p in (task / "children").read_text().split()]
        except (OSError, ValueError):
            pass
    return out


def _emulator_pid(session_pid: int) -> int | None:
    for pid in _children(session_pid):
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if b"emulators" in cmdline:
            return pid
    return None


def _kill_rig_while(argv: list[str], marker: bytes) -> tuple[int, str, str]:
    """Run the teleop CLI with ``argv`` in a process of its own; when its progress line shows
    ``marker`` (printed once a second), kill its emulator process. Returns (exit code,
    stdout, stderr)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "beavr_sim.teleop", *argv],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    err = b""
    killed = None
    try:
        while killed is None:  # the session's own word that it runs, then the kill
            chunk = proc.stderr.read1(4096)
            if not chunk:
                break
            err += chunk
            lines = err.replace(b"\r", b"\n").split(b"\n")
            if any(marker in line and b"t=" in line for line in lines[:-1]):
                killed = _emulator_pid(proc.pid)
                assert killed is not None, "the emulator process was not found"
                os.kill(killed, signal.SIGKILL)
        out, rest = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = (err + rest).decode(errors="replace")
    assert killed is not None, text[-2000:]
    return proc.returncode, out.decode(), text


def _check_dead_rig_ending(code: int, err: str) -> None:
    assert code == EXIT_DEVICE_FAILED, err[-2000:]
    assert "Traceback" not in err, err[-4000:]
    # the vendor SDK's own error lines repeat our one line (only with --debug)
    assert "[SDK][ERROR]" not in err, err[-4000:]
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "failed" in errors[0], errors


def test_dead_rig_ends_the_session_non_zero_with_one_line():
    """Item 4: the emulators are killed during the first of ``--repeat 2`` runs. The session
    ends with exit code 4 (was 0, playing on) and one line naming the failed device, no
    Python traceback; the summary names the failed devices and covers the run."""
    code, out, err = _kill_rig_while(
        ["--task", "pickup_box", "--source", "trace", *MIRRORED, "--repeat", "2"], b"t="
    )
    _check_dead_rig_ending(code, err)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["failed_devices"], summary
    assert summary["runs"] == 1 and summary["per_run"][0]["hardware_fault"]
    assert summary["stopped_early"]


def test_episode_on_a_dead_rig_is_kept_only_marked_as_a_fault(tmp_path):
    """Item 2's other half: the rig dies while an episode records. With
    ``--keep-faulty-episodes`` the episode is kept, marked ``hardware_fault`` (never a normal
    success), the session ends (no episode recorded on a dead rig) with exit code 4."""
    root = tmp_path / "D"
    code, out, err = _kill_rig_while(
        ["--task", "pickup_box", "--source", "trace", *MIRRORED, "--record", str(root),
         "--repo-id", "test/dead", "--episodes", "2", "--cameras", "none", "--no-keypoints",
         "--keep-faulty-episodes"],
        b"episode 1/2: REC",
    )  # fmt: skip
    _check_dead_rig_ending(code, err)
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["failed_devices"], summary
    assert summary["hardware_faults"] >= 1 and summary["successes"] == 0
    faulty = summary["per_run"][0]
    assert faulty["hardware_fault"] and faulty["saved"] is True
    log = [json.loads(line) for line in (root / "meta" / "beavr_episodes.jsonl").open()]
    assert len(log) == 1  # the session ended: no episode 2 on a dead rig
    assert log[0]["kept"] and log[0]["hardware_fault"] and log[0]["success"] is False
    assert "HARDWARE FAULT" in err


def test_loading_a_recorded_dataset_prints_no_traceback(tmp_path):
    """Item 8: a dataset is read back without LeRobot's torchcodec probe (its traceback when
    the system's FFmpeg libraries are missing): the project opens datasets with PyAV."""
    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    env.reset(seed=0)
    config = RecordingConfig(cameras=("front",), image_height=48, image_width=64)
    writer = EpisodeWriter(
        tmp_path / "ds",
        "test/load",
        lerobot_features(env.embodiment, config, env.environment_state_names),
        config.fps,
        robot_type=env.embodiment.name,
    )
    recorder = EpisodeRecorder(writer, env, config)
    recorder.begin()

    class _State:
        action = env.joints.home.copy()

    for _ in range(3):
        recorder(Tick(t=0.0, frames=(), commands={}, state=_State()))  # type: ignore[arg-type]
    assert recorder.end(keep=True)
    recorder.close()
    writer.close()
    env.close()
    code = (
        "from beavr_sim.datasets.writer import open_dataset\n"
        f"ds = open_dataset({str(tmp_path / 'ds')!r})\n"
        "item = ds[1]\n"
        "print(ds.num_episodes, tuple(item['observation.images.front'].shape))\n"
    )
    env_vars = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, env=env_vars, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split()[0] == "1"
    assert "Traceback" not in done.stderr and "torchcodec" not in done.stderr, done.stderr[-3000:]


def test_session_options_check_the_new_rig_options():
    from beavr_sim.teleop.session import SessionOptions

    with pytest.raises(ValueError, match="needs --record"):
        SessionOptions(task="pour", source="trace", keep_faulty_episodes=True)
    with pytest.raises(ValueError, match="emulated"):
        SessionOptions(task="pour", source="trace", emulate_faults="freeze xarm 2s")
    with pytest.raises(ValueError, match="one line"):
        SessionOptions(
            task="pour",
            source="trace",
            mirror_hardware=True,
            hardware_config="emulated",
            emulate_faults="freeze\nall",
        )
    with pytest.raises(ValueError, match="sync-timeout"):
        SessionOptions(
            task="pour",
            source="trace",
            mirror_hardware=True,
            hardware_config="emulated",
            sync_timeout_s=0,
        )
    ok = SessionOptions(
        task="pour",
        source="trace",
        mirror_hardware=True,
        hardware_config="emulated",
        emulate_faults="  right_arm:freeze=2@5 ",
    )
    assert ok.emulate_faults == "right_arm:freeze=2@5"


@pytest.mark.parametrize(
    "layout", [[], ["--multiprocess", "--clock", "paced"]], ids=["one_process", "multiprocess"],
)  # fmt: skip
def test_emulated_faults_are_rehearsed_through_the_cli(capsys, layout):
    """``--emulate-faults``: the hand's bus stops answering for 2 s, 3 s into the session; the
    rig holds, the hand comes back within ``reconnect_s`` and the session goes on. The run is
    reported as one with a hardware fault, the device's outage as recovered; nothing failed.
    In both layouts (main refused it with --multiprocess), the run starting from a synced rig."""
    code = teleop_main(
        ["--task", "pour", "--source", "trace", *MIRRORED, "--quiet",
         "--emulate-faults", "right_hand:freeze=2@3", *layout]
    )  # fmt: skip
    summary = _summary(capsys)
    assert code == 0, summary
    assert summary["per_run"][0]["sync_s"] >= 0, summary["per_run"]
    hand = summary["hardware"]["right_hand"]
    assert hand["outages"] >= 1 and hand["recovered"] >= 1, hand
    assert summary["failed_devices"] == []
    assert any(r["hardware_fault"] for r in summary["per_run"]), summary["per_run"]
    assert hand["state"] == "following" and hand["connected"], hand
    # the twin poured, the rig held 2 s of it: not a success, the twin's outcome said apart
    faulty = summary["per_run"][-1]
    assert faulty["hardware_fault"] and faulty["success"] is False, faulty
    assert faulty["task_success"] is True and summary["task_success"] is True, faulty
    assert summary["success"] is False and summary["successes"] == 0, summary


def test_a_bad_fault_spec_is_one_line_naming_the_choices(capsys):
    code = teleop_main(
        ["--task", "pour", "--source", "trace", *MIRRORED, "--quiet",
         "--emulate-faults", "right_hand:melt=2"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2
    line = [ln for ln in err.splitlines() if "melt" in ln]
    assert len(line) == 1 and "freeze" in line[0] and "Traceback" not in err, err


def test_help_documents_the_exit_codes(capsys):
    with pytest.raises(SystemExit):
        teleop_main(["--help"])
    text = capsys.readouterr().out
    for line in ("exit codes:", "4  a mirrored device failed", "--debug", "--keep-faulty-episodes"):
        assert line in text
