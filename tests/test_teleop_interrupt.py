"""Ctrl-C and SIGTERM end a teleop session in order: the JSON summary is still printed and
written (marked interrupted), the exit code is 128 + the signal, finished episodes are saved and
the one in progress is not; an idle live recording ends at --max-seconds; recording into an
existing dataset says it appends.

Each session runs as a subprocess; the signal is sent once its stderr shows it reached the
point under test (a readiness line, never a fixed sleep)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from beavr_sim.teleop.interrupt import StopSignal, stop_on_signals

ROOT = Path(__file__).resolve().parents[1]
#: A hang guard only (the test fails, never waits forever): no timing is asserted.
HANG_S = 300
TRACE_SESSION = ("--task", "pour", "--source", "trace", "--headless", "--no-viser")


class Session:
    """``python -m beavr_sim.teleop ARGS`` with its stderr read in a thread."""

    def __init__(self, *args: str):
        env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "beavr_sim.teleop", *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=ROOT,
        )
        self.err = ""
        self.out: list[str] = []
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        # stdout in a thread of its own, so that a session that never exits fails the test
        # (bounded waits below) instead of blocking a read forever
        self._out_reader = threading.Thread(
            target=lambda: self.out.append(self.proc.stdout.read()), daemon=True
        )
        self._out_reader.start()

    def _read(self) -> None:
        while chunk := self.proc.stderr.read(1):
            with self._changed:
                self.err += chunk
                self._changed.notify_all()
        with self._changed:
            self.err += "\0"  # end of stream
            self._changed.notify_all()

    def wait_for(self, text: str) -> None:
        with self._changed:
            seen = self._changed.wait_for(lambda: text in self.err or "\0" in self.err, HANG_S)
        if not seen or text not in self.err:
            self.proc.kill()
            pytest.fail(f"the session never printed {text!r}; stderr:\n{self.err[-2000:]}")

    def finish(self) -> tuple[int, dict]:
        try:
            self.proc.wait(timeout=HANG_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            pytest.fail(f"the session did not exit within {HANG_S} s; stderr:\n{self.err[-2000:]}")
        self._out_reader.join(HANG_S)
        self._reader.join(HANG_S)
        lines = "".join(self.out).strip().splitlines()
        assert lines, f"no summary on stdout; stderr:\n{self.err[-2000:]}"
        return self.proc.returncode, json.loads(lines[-1])


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_ends_the_session_with_its_summary(tmp_path, sig, code):
    out = tmp_path / "summary.json"
    session = Session(*TRACE_SESSION, "--repeat", "0", "--summary-json", str(out))
    session.wait_for("\nrun 1:")  # a run ended; the trace plays again until the signal
    session.proc.send_signal(sig)
    rc, summary = session.finish()
    assert rc == code, session.err[-2000:]
    assert summary["interrupted"] is True
    assert summary["ended_by"] == sig.name
    assert summary["runs"] >= 1 and summary["per_run"][0]["success"] is True
    assert out.exists(), "--summary-json not written"
    assert json.loads(out.read_text()) == summary


def test_an_interrupted_recording_keeps_finished_episodes_only(tmp_path):
    dataset = tmp_path / "ds"
    # paced: episode 2 lasts the trace's real length, so the signal sent once it started lands
    # inside it however late it is delivered (the virtual clock could finish it first)
    session = Session(
        *TRACE_SESSION,
        *("--clock", "paced", "--record", str(dataset), "--episodes", "3", "--cameras", "none"),
    )
    session.wait_for("episode 2/3: REC")  # episode 1 saved, episode 2 recording
    session.proc.send_signal(signal.SIGINT)
    rc, summary = session.finish()
    assert rc == 130, session.err[-2000:]
    assert summary["interrupted"] is True and summary["ended_by"] == "SIGINT"
    log = [json.loads(line) for line in (dataset / "meta" / "beavr_episodes.jsonl").open()]
    kept = [r for r in log if r["kept"]]
    assert kept and all(r["ended_by"] == "auto" for r in kept), log
    assert log[-1]["kept"] is False and log[-1]["ended_by"] == "interrupted", log
    assert log[-1]["success"] is False
    info = json.loads((dataset / "meta" / "info.json").read_text())
    assert info["total_episodes"] == len(kept) < 3
    assert summary["successes"] == len(kept)
    # the same trace recorded 3 times: said once, with where varied demonstrations come from
    assert session.err.count("records the same demonstration 3 times") == 1
    assert "python -m beavr_sim.datasets generate --task Pour --episodes 3" in session.err


def test_recording_into_an_existing_dataset_says_it_appends(tmp_path):
    dataset = tmp_path / "ds"
    args = (*TRACE_SESSION, "--record", str(dataset), "--cameras", "none", "--quiet")
    # the first run saves its whole episode (no time limit: a loaded machine must not matter);
    # the second only needs to open the dataset
    for run, extra in ((1, ()), (2, ("--max-seconds", "0.3"))):
        session = Session(*args, *extra)
        rc, _ = session.finish()
        assert rc == 0, session.err[-2000:]
        if run == 1:
            info = json.loads((dataset / "meta" / "info.json").read_text())
            assert info["total_episodes"] == 1, info
        said = "appending to the 1 episodes already there" in session.err
        assert said is (run == 2), session.err[-2000:]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_idle_live_recording_ends_at_max_seconds(tmp_path):
    """No operator frames ever arrive (a WebXR page nobody opens): the session still ends at
    --max-seconds, with nothing recorded."""
    session = Session(
        "--task",
        "pour",
        "--source",
        "webxr",
        "--webxr-port",
        str(_free_port()),
        "--headless",
        "--no-viser",
        "--record",
        str(tmp_path / "ds"),
        "--max-seconds",
        "0.5",
        "--cameras",
        "none",
        "--quiet",
    )
    rc, summary = session.finish()
    assert rc == 0, session.err[-2000:]
    assert summary["runs"] == 0 and summary["frames_received"] == 0
    assert summary["duration_s"] == pytest.approx(0.5, abs=0.05)


def test_the_first_signal_stops_in_order_the_second_aborts():
    stop = StopSignal()
    before = signal.getsignal(signal.SIGTERM)
    with stop_on_signals(stop):
        signal.raise_signal(signal.SIGTERM)
        assert stop() and stop.name == "SIGTERM" and stop.exit_code == 143
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGTERM) is before  # the previous handler is back
