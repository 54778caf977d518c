"""``--record`` and ``--repeat`` under ``--multiprocess`` (issue 37): the twin process plays the
session's runs (``teleop/twin_runs.py``) with the same per-run decisions as one process
(``teleop/runs.py``), its recorder fed the operator's keypoints of each tick over the wire.

On the virtual clock the layouts are compared frame for frame: the same trace recorded in
one process and in two gives the same ``action``, ``observation.state`` and hand keypoints,
bit for bit, episode by episode, and a ``--repeat`` session the same commands every tick.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from fixtures_shared import cut_bundled_trace, trace_session_options
from recorded_state import check_follows, read_episodes
from websockets.sync.client import connect

import beavr_sim
from beavr_sim.cameras.stream import LIVE
from beavr_sim.datasets.features import ACTION, KEYPOINTS, STATE, TRACKED, RecordingConfig
from beavr_sim.headset.layouts import LAYOUTS
from beavr_sim.headset.webxr_protocol import encode_hands
from beavr_sim.teleop.episodes import session_command
from beavr_sim.teleop.processes import MultiprocessSession
from beavr_sim.teleop.session import SessionOptions, run_session
from beavr_sim.wire.hand import N_JOINTS
from beavr_sim.wire.ports import PortConfig, TransportConfig

#: The checkout whose package these tests import (subprocesses run the same code).
REPO = Path(beavr_sim.__file__).resolve().parents[1]
#: The mirrored session of the frozen-rig test, run in a process of its own (free ports: the
#: CLI's standard ones may be taken by another session on this machine).
FROZEN_RIG_SESSION = """
import json, sys
from pathlib import Path
from beavr_sim.datasets.features import RecordingConfig
from beavr_sim.teleop.session import SessionOptions, run_session
from beavr_sim.wire.ports import PortConfig, TransportConfig
options = SessionOptions(
    task="PickupBox", source="trace", mirror_hardware=True, hardware_config="emulated",
    viser=False, headless=True, multiprocess=True, clock="paced", record=Path(sys.argv[1]),
    repo_id="test/frozen", episodes=1,
    recording=RecordingConfig(cameras=(), episode_seconds=2.0, use_videos=False),
    transport=TransportConfig(ports=PortConfig.free()),
)
print(json.dumps(run_session(options).to_dict()))
"""
#: Seconds of the bundled PickupBox trace kept: each run is this plus the 2 s a run plays on
#: after its source ended.
CUT_S = 0.7
RECORDING = RecordingConfig(cameras=(), use_videos=False)


@pytest.fixture(scope="module")
def short_trace(tmp_path_factory):
    """The bundled PickupBox trace cut after :data:`CUT_S` seconds."""
    return cut_bundled_trace(tmp_path_factory.mktemp("trace") / "short.mcap", CUT_S)


def options(trace, multiprocess: bool, **kwargs) -> SessionOptions:
    return trace_session_options(
        trace,
        multiprocess=multiprocess,
        transport=TransportConfig(ports=PortConfig.free()),
        **kwargs,
    )


def recorded(root) -> dict[str, np.ndarray]:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("test/mp", root=root, video_backend="pyav")
    keys = (ACTION, STATE, KEYPOINTS, TRACKED, "episode_index", "frame_index")
    return {k: np.array(ds.hf_dataset[k]) for k in keys}


def episode_log(root) -> list[dict]:
    lines = (root / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    return [json.loads(line) for line in lines]


def test_a_trace_records_the_same_episodes_in_both_layouts(short_trace, tmp_path):
    """Two recorded episodes of a trace (each from a reset, the trace played from its start)
    in one process and with --multiprocess: the same frames, bit for bit (main refused
    --record with --multiprocess)."""
    summaries, data = {}, {}
    for multiprocess in (False, True):
        root = tmp_path / f"multi{int(multiprocess)}"
        opts = options(
            short_trace,
            multiprocess,
            record=root,
            repo_id="test/mp",
            episodes=2,
            recording=RECORDING,
        )
        summaries[multiprocess] = run_session(opts)
        data[multiprocess] = recorded(root)
        assert [r["kept"] for r in episode_log(root)] == [True, True]
    one, multi = summaries[False], summaries[True]
    assert multi.processes == {"twin": "ok", "operator": "ok"}
    assert np.unique(data[True]["episode_index"]).tolist() == [0, 1]
    assert data[True][TRACKED].any(), "the hands were tracked: keypoints were recorded"
    for key, expected in data[False].items():
        np.testing.assert_array_equal(data[True][key], expected, err_msg=key)
    # each episode is the trace from its start: the two are the same demonstration
    first = data[True]["episode_index"] == 0
    np.testing.assert_array_equal(data[True][KEYPOINTS][first], data[True][KEYPOINTS][~first])
    assert (multi.runs, multi.successes, multi.per_run) == (one.runs, one.successes, one.per_run)
    assert multi.runs == 2 and multi.stopped_early == ""


def digest_ticks(process, path: str):
    """An attachment: the digest of every lockstep tick's commands, written at the end."""
    digest = hashlib.sha256()

    def after_step(state) -> None:
        for name in sorted(process.tick_commands):
            command = process.tick_commands[name]
            digest.update(np.asarray(command.positions, dtype=np.float64).tobytes())
            digest.update(bytes([command.hold]) + command.reason.encode())

    process.stage.after_step.append(after_step)

    def finish() -> None:
        with open(path, "w") as f:
            f.write(digest.hexdigest())

    return finish


def test_a_repeated_trace_plays_the_same_runs_in_both_layouts(short_trace, tmp_path):
    """``--repeat 2`` with --multiprocess (main refused it): the trace played twice from a
    reset, every tick's commands as in one process, the summary's runs the same."""
    from beavr_sim.teleop.process_config import Attachment
    from beavr_sim.teleop.processes import MultiprocessSession

    digest = hashlib.sha256()

    def on_loop(loop) -> None:
        def listener(tick) -> None:
            for name in sorted(tick.commands):
                command = tick.commands[name]
                digest.update(np.asarray(command.positions, dtype=np.float64).tobytes())
                digest.update(bytes([command.hold]) + command.reason.encode())

        loop.listeners.append(listener)

    one = run_session(options(short_trace, False, repeat=2), on_loop=on_loop)
    multi_options = options(short_trace, True, repeat=2)
    path = tmp_path / "digest.txt"
    session = MultiprocessSession(
        multi_options, attach=(Attachment(f"{__name__}:digest_ticks", str(path)),)
    )
    multi = session.run(multi_options.max_seconds, stop_on_success=True)
    assert multi.processes == {"twin": "ok", "operator": "ok"}
    assert path.read_text() == digest.hexdigest()
    assert multi.runs == one.runs == 2
    assert multi.per_run == one.per_run
    assert multi.run_totals == one.run_totals


# ------------------------------------------------------------------ on the emulated rig
def _descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        for task in Path(f"/proc/{todo.pop()}/task").glob("*"):
            try:
                children = [int(p) for p in (task / "children").read_text().split()]
            except (OSError, ValueError):
                continue
            out += children
            todo += children
    return out


def _emulator_pid(session_pid: int) -> int | None:
    """The emulated rig's process (a child of the twin process)."""
    for pid in _descendants(session_pid):
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"emulators" in cmdline:
            return pid
    return None


def test_a_frozen_rig_spoils_the_episode_it_records_and_the_next_starts_synced(tmp_path):
    """Mirrored --multiprocess recording (main refused it): the emulated rig's process is
    frozen (SIGSTOP) the moment the first episode starts recording and let go (SIGCONT) when
    the session says how the episode ended. That episode is discarded, never saved; the
    rig recovers, syncs, and the episode is recorded again from its start, true (its measured
    state follows its commands) and as long as asked (no frame of the sync in it)."""
    root = tmp_path / "D"
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    proc = subprocess.Popen(
        [sys.executable, "-c", FROZEN_RIG_SESSION, str(root)],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    err, frozen, released = b"", None, False
    try:
        while not released:  # the session's own words: recording, then the fault
            chunk = proc.stderr.read1(4096)
            if not chunk:
                break
            err += chunk
            if frozen is None and b"episode 1/1: REC\n" in err:
                frozen = _emulator_pid(proc.pid)
                assert frozen is not None, "the emulator process was not found"
                os.kill(frozen, signal.SIGSTOP)
            if frozen is not None and err.count(b"episode 1/1: ") >= 2:  # its end line
                os.kill(frozen, signal.SIGCONT)
                released = True
        out, rest = proc.communicate(timeout=300)
    finally:
        if frozen is not None and not released:
            os.kill(frozen, signal.SIGCONT)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = (err + rest).decode(errors="replace")
    assert released and proc.returncode == 0, text[-3000:]
    summary = json.loads(out.decode().strip().splitlines()[-1])
    log = episode_log(root)
    # The frozen run, then the true one (a busy machine may spoil a run more: retried too).
    spoilt = [(False, True)] * (len(log) - 1)
    assert [(r["kept"], bool(r["hardware_fault"])) for r in log] == [*spoilt, (True, False)], log
    assert len(log) >= 2 and log[-1]["frames"] == 2 * 30, log  # the episode only: no sync
    runs = summary["per_run"]
    assert [(r["saved"], bool(r["hardware_fault"])) for r in runs] == [*spoilt, (True, False)]
    assert all(r["sync_s"] >= 0 for r in runs), runs  # each run started from a synced rig
    assert summary["failed_devices"] == [] and summary["stopped_early"] == ""
    ((state, action, names),) = read_episodes(root, "test/frozen").values()
    check_follows(state, action, names, 1)  # the arm followed, by the rig's own rule


def _rerun_rows(path) -> tuple[dict[str, int], dict[str, list]]:
    """Rows per entity path on the timelines, and each entity's values (``Scalars`` or
    ``Points3D`` positions) in tick order."""
    import rerun as rr

    rows: dict[str, int] = {}
    values: dict[str, list] = {}
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        if chunk.is_static:
            continue
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        batch = chunk.to_record_batch()
        for column in ("Scalars:scalars", "Points3D:positions"):
            if column in batch.schema.names:
                ticks = batch.column("tick").to_pylist()
                got = values.setdefault(chunk.entity_path, [])
                got += list(zip(ticks, batch.column(column).to_pylist(), strict=True))
    return rows, {k: [v for _, v in sorted(vs, key=lambda x: x[0])] for k, vs in values.items()}


def test_a_rerun_log_of_the_twin_process_holds_what_one_process_logs(short_trace, tmp_path):
    """``--rerun`` with --multiprocess (main refused it): the logger follows the twin stage's
    ``after_step`` hook. On the virtual clock the log holds every tick's joints, commands and
    holds, and the hands the operator saw, with the values one process logs."""
    logs = {}
    for multiprocess in (False, True):
        path = tmp_path / f"session{int(multiprocess)}.rrd"
        opts = options(short_trace, multiprocess, rerun=path, rerun_image_hz=0, rerun_twin_hz=0)
        summary = run_session(opts)
        logs[multiprocess] = _rerun_rows(path)
    (rows_one, one), (rows_multi, multi) = logs[False], logs[True]
    ticks = summary.ticks
    for entity in (
        "/robot/joints/right/joint1/position",
        "/robot/joints/right/leap_15/command",
        "/robot/hold/right",
        "/task/success",
    ):
        assert rows_multi.get(entity) == rows_one.get(entity) == ticks, entity
        assert multi[entity] == one[entity], entity
    hands = "/world/hands/right/keypoints"
    assert rows_multi.get(hands) == rows_one.get(hands) > ticks // 4
    assert multi[hands] == one[hands]


def test_a_live_webxr_session_records_the_episode_its_gesture_starts_and_a_request_stops(
    tmp_path,
):
    """--source webxr --record --multiprocess (main refused live recording there): the twin
    idles, following the hands, until the operator's long left pinch (forwarded as an operator
    event) starts an episode; the supervisor's stop request (the keyboard's session command)
    saves it: one episode, with the hand frames sent while it recorded. The twin's camera panel
    (--camera-stream-hz, streamed from the twin process) reaches the page."""
    root = tmp_path / "live"
    opts = SessionOptions(
        task="PickupBox",
        embodiment="rx1",
        source="webxr",
        viser=False,
        headless=True,
        progress=False,
        multiprocess=True,
        record=root,
        repo_id="test/mp",
        recording=RECORDING,
        camera_stream_hz=10.0,  # the twin's camera panel, streamed from the twin to the page
        transport=TransportConfig(ports=PortConfig.free()),
    )
    rng = np.random.default_rng(0)
    canonical = np.array([0.3, 0.0, 1.1]) + rng.uniform(-0.09, 0.09, size=(N_JOINTS, 3))
    hand = LAYOUTS["webxr25"].from_canonical(canonical)
    hands = {"left": hand, "right": hand}
    session = MultiprocessSession(opts)
    session.start()

    def state_where(ok, what: str):
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline:
            state = session.state_sub.recv_latest(0.5)
            if state is not None and ok(state):
                return state
        raise AssertionError(f"the twin never {what}")

    sent = 0
    try:
        with connect(f"ws://127.0.0.1:{opts.webxr_config().port}/ws") as ws:
            assert json.loads(ws.recv())["type"] == "welcome"

            def send(pinch_left: bool) -> None:
                nonlocal sent
                pinch = {"left": pinch_left, "right": False}
                ws.send(encode_hands(1.7e12 + 33 * sent, hands, seq=sent, pinch=pinch))
                sent += 1

            assert state_where(lambda s: s.tick == -1, "published").run == 0  # idle
            for i in range(45):  # a left pinch held 1.4 s (source time), then let go
                send(pinch_left=i < 42)
            state_where(lambda s: s.run == 1, "started the episode on the gesture")
            for _ in range(15):  # a frame a control tick while it records
                state_where(lambda s: True, "ticked")
                send(pinch_left=False)
            session.send(session_command("stop"))
            state_where(lambda s: s.done, "ended the session after the saved episode")
            # The panels the page got, in order. A panel composed before the twin's first pose
            # copy, or rendered more than dead_after_s after it on a busy machine, is rightly
            # "no signal"; a live one must have reached the page while the twin ticked.
            states: list[str] = []
            deadline = time.monotonic() + 60.0
            while LIVE not in states:
                assert time.monotonic() < deadline, (
                    f"no live camera panel reached the page ({len(states)} panels, all {set(states)})"
                )
                message = json.loads(ws.recv(timeout=60.0))
                if message["type"] == "camera":
                    states.append(message["state"])
                    assert message["jpeg"], "a camera panel came without its image"
    finally:
        session.stop()
    op, twin = session.results["operator"], session.results["twin"]
    assert op["record_events"] == 1 and op["detector"]["frames_received"] == 2 * sent
    assert twin["runs"]["runs"] == 1 and twin["stopped_early"] == ""
    assert [r["kept"] for r in episode_log(root)] == [True]
    data = recorded(root)
    assert np.unique(data["episode_index"]).tolist() == [0] and len(data[ACTION]) > 0
    assert data[TRACKED].any(), "the hand frames sent while it recorded are in the episode"
