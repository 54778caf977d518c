"""The teleop pipeline end to end: bundled VR traces, the CLI, a fake headset, processes."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest
import zmq

from beavr_sim.assets import bundled_trace
from beavr_sim.tasks.registry import TASKS
from beavr_sim.teleop.session import SessionOptions, build_loop
from beavr_sim.traces.format import TraceReader
from beavr_sim.wire.ports import PortConfig, TransportConfig

BENCHMARK_TASKS = [t for t in TASKS if t != "Playground"]


def replay(task: str, **kwargs):
    options = SessionOptions(
        task=task, source="trace", viser=False, headless=True, progress=False, **kwargs
    )
    loop = build_loop(options)
    summary = loop.run()
    q = loop.twin.env.data.qpos.copy()
    loop.twin.env.close()
    return summary, q


@pytest.mark.parametrize("task", BENCHMARK_TASKS)
def test_bundled_trace_replays_to_task_success(task):
    path = bundled_trace(task)
    assert path.is_file(), f"no bundled trace for {task}: {path}"
    meta = TraceReader(path).metadata
    assert meta.task == task and meta.source == "synth"
    summary, _ = replay(task)
    assert summary.success, summary
    assert summary.frames_rejected == 0
    assert summary.commands_applied > 0


RX1_TASKS = ["PickPlace", "PickupBox", "StackBlocks", "Pour"]


@pytest.mark.parametrize("task", RX1_TASKS)
def test_rx1_bundled_trace_replays_to_task_success(task):
    """Both VR hands drive both RX-1 arms and LEAP hands through the same operator."""
    path = bundled_trace(task, "rx1")
    assert path.is_file(), f"no bundled RX-1 trace for {task}: {path}"
    meta = TraceReader(path).metadata
    assert (meta.task, meta.embodiment, meta.source) == (task, "rx1", "synth")
    summary, _ = replay(task, embodiment="rx1")
    assert summary.success, summary
    assert summary.frames_rejected == 0
    assert set(summary.operator) == {"left", "right"}
    assert all(op["frames"] > 0 for op in summary.operator.values())


def test_replay_is_deterministic():
    a, qa = replay("PickupBox")
    b, qb = replay("PickupBox")
    np.testing.assert_array_equal(qa, qb)
    assert (a.success, a.ticks, a.commands_applied) == (b.success, b.ticks, b.commands_applied)


def test_cli_writes_the_summary_json(tmp_path, capsys):
    from beavr_sim.teleop.__main__ import main

    out = tmp_path / "summary.json"
    rc = main(
        [
            "--task",
            "pickup_box",
            "--source",
            "trace",
            "--no-viser",
            "--headless",
            "--quiet",
            "--summary-json",
            str(out),
        ]
    )
    assert rc == 0
    report = json.loads(out.read_text())
    assert report == json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in (
        "task",
        "embodiment",
        "success",
        "frames_received",
        "frames_rejected",
        "commands_applied",
        "duration_s",
        "latency_ms",
    ):
        assert key in report
    assert report["success"] is True and report["task"] == "PickupBox"
    assert set(report["latency_ms"]) >= {"p50", "p99"} and report["latency_ms"]["p50"] > 0


def test_cli_summary_json_dash_means_stdout_not_a_file(tmp_path, capsys, monkeypatch):
    from beavr_sim.teleop.__main__ import main

    monkeypatch.chdir(tmp_path)
    args = ["--task", "pickup_box", "--source", "trace", "--no-viser", "--headless", "--quiet"]
    assert main([*args, "--summary-json", "-"]) == 0
    assert not (tmp_path / "-").exists()
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["task"] == "PickupBox"


def test_cli_rejects_bad_arguments_with_clear_errors(capsys, tmp_path):
    from beavr_sim.assets import bundled_trace
    from beavr_sim.teleop.__main__ import main

    assert main(["--task", "poor", "--source", "trace", "--no-viser"]) == 2
    assert "Did you mean 'Pour'" in capsys.readouterr().err
    assert main(["--task", "pour", "--source", "trace", "--trace", str(tmp_path / "x.mcap")]) == 2
    assert "not found" in capsys.readouterr().err
    assert (
        main(
            ["--task", "pour", "--source", "trace", "--embodiment", "xarm7_leap_left", "--no-viser"]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "Pour does not run on xarm7_leap_left (runs on xarm7_leap_right" in err
    trace = str(bundled_trace("pour"))
    args = ["--task", "pour", "--source", "trace", "--trace", trace, "--no-viser"]
    assert main([*args, "--embodiment", "xarm7_leap_left"]) == 2
    assert "drives xarm7_leap_right" in capsys.readouterr().err


def test_fake_headset_drives_the_twin_and_bad_payloads_are_only_counted(quest_push, quest_options):
    """The Quest source end to end: a PUSH socket per stream like the app, real keypoint
    strings (from a bundled trace) and malformed ones, in real time."""
    from beavr_sim.headset.quest_protocol import format_keypoints

    options = quest_options()
    transport, context = options.transport, zmq.Context()
    loop = build_loop(options, context)
    push = quest_push(context, transport)
    frames = [f for _, k, f in TraceReader(bundled_trace("PickupBox")).events() if k == "hand"]
    q0 = loop.twin.env.agent_pos.copy()
    bad = [
        b"garbage",
        b"absolute:1,2,3:",
        ("absolute:" + "|".join(["0,1,0,2,0,3"] * 26) + ":").encode(),
    ]
    try:
        for i, frame in enumerate(frames[60:240]):
            push.send(format_keypoints(frame).encode())
            if i % 50 == 10:
                push.send(bad[(i // 50) % len(bad)])
            time.sleep(1 / 60)
            if i % 2:
                loop.tick()
        for _ in range(10):
            time.sleep(1 / 30)
            loop.tick()
        summary = loop.summary(success=False)
    finally:
        push.close()
        loop.source.close()
        loop.twin.env.close()
        context.term()
    assert summary.frames_received > 30
    assert summary.frames_rejected >= 3
    assert set(summary.rejected_by_reason) >= {"no_marker", "wrong_joint_count", "comma_decimal"}
    moved = np.abs(loop.twin.env.agent_pos - q0).max()
    assert moved > 0.05, "the twin did not follow the headset"


def twin_state_at(session, t: float, timeout_s: float = 120.0):
    """The twin's first published state at or after its time ``t`` (s of simulated time: a
    busy machine slows the twin down, it does not make it skip this wait)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = session.state_sub.recv_latest(0.5)
        if state is not None and state.t >= t:
            return state
    raise AssertionError(f"the twin did not reach t = {t:.2f} s within {timeout_s:.0f} s")


def test_killing_the_operator_process_leaves_the_others_alive_and_the_robot_holding():
    from beavr_sim.teleop.processes import MultiprocessSession

    options = SessionOptions(
        task="PickupBox",
        source="trace",
        viser=False,
        headless=True,
        progress=False,
        multiprocess=True,
        transport=TransportConfig(ports=PortConfig.free()),
    )
    session = MultiprocessSession(options)
    session.start()
    try:
        twin_state_at(session, 3.0)  # 3 s into the trace
        os.kill(session.processes["operator"].pid, signal.SIGKILL)
        session.processes["operator"].join(30.0)
        killed = twin_state_at(session, 0.0)
        # The arm settles on the last targets it was given (1 s of the twin's time), then
        # holds them for another second.
        first = twin_state_at(session, killed.t + 1.0)
        last = twin_state_at(session, first.t + 1.0)
        arm = slice(0, 7)
        held = np.abs(np.subtract(last.positions, first.positions)[arm]).max()
        assert held < 2e-3, f"arm moved {held} rad after the operator died"
        assert session.dead() == ["operator"]
    finally:
        session.stop()
    assert session.exits["operator"] == -signal.SIGKILL
    assert session.exits["twin"] == 0


@pytest.mark.parametrize("multiprocess", [False, True], ids=["one_process", "multiprocess"])
def test_live_session_shows_the_twin_in_the_headset(multiprocess):
    """--source quest without --headless: rendered twin images on the camera stream (PUB),
    JPEG at the configured size; with no headset connected the robot holds. In
    --multiprocess the twin process renders and publishes them (main ignored them there)."""
    import io
    import threading

    from PIL import Image

    from beavr_sim.teleop.session import run_session

    transport = TransportConfig(ports=PortConfig.free())
    options = SessionOptions(
        task="PickupBox",
        source="quest",
        viser=False,
        headless=False,
        progress=False,
        transport=transport,
        max_seconds=2.5,
        headset_image_hz=10.0,
        headset_image_size=(320, 180),
        multiprocess=multiprocess,
    )
    result = {}
    runner = threading.Thread(target=lambda: result.update(summary=run_session(options)))
    context = zmq.Context()
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.setsockopt(zmq.LINGER, 0)
    sub.connect(transport.endpoint("headset_camera", bind=False))
    runner.start()
    try:
        # (the processes start within a minute on a busy machine: the session's own limit)
        assert sub.poll(60_000 if multiprocess else 5000), "no image reached the headset stream"
        image = Image.open(io.BytesIO(sub.recv()))
        assert image.format == "JPEG" and image.size == (320, 180)
    finally:
        runner.join(10.0)
        sub.close()
        context.term()
    summary = result["summary"]
    assert summary.frames_received == 0 and summary.commands_applied == 0
    assert summary.holds["right"].get("waiting", 0) > 0
    assert summary.listener_errors == {}


def test_repeat_plays_the_trace_again_from_its_start(capsys):
    """The second play's timestamps start over: none is rejected as out of order, and the
    episode succeeds again (the summary is the last run's)."""
    from beavr_sim.teleop.__main__ import main

    args = ["--task", "pickup_box", "--source", "trace", "--no-viser", "--headless"]
    assert main([*args, "--repeat", "2", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["success"] and summary["frames_rejected"] == 0
