"""The per-frame stages (``teleop/stages.py``) and the runners built on them.

``EXPECTED`` was recorded by running main at 0ac0037 (before the stages existed) with the
code of :func:`replay_digest` below, run on main's tree: a bundled trace replayed on the
virtual clock, every summary field but wall time (``loop_rate_hz``, the latency percentiles;
their count is kept), plus a digest of every command (positions, hold, reason) and of the
final ``qpos``. The digests hold for this machine's MuJoCo and numpy builds.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import time

import numpy as np
import pytest

from beavr_sim.teleop.session import SessionOptions, build_loop

EXPECTED = {
    "PickupBox/None": {
        "commands_applied": 269,
        "commands_sha256": "785a83b6413f78afec054a35b7a3068c49c0f7a82cc10c30589584ec6d14c65e",
        "duration_s": 8.966666666666667,
        "embodiment": "xarm7_leap_right",
        "frames_received": 534,
        "frames_rejected": 0,
        "frames_superseded": 0,
        "guard_blocks": {},
        "hardware": {},
        "holds": {},
        "latency_ms": {"n": 268},
        "listener_errors": {},
        "missed_ticks": 0,
        "operator": {
            "right": {
                "errors": 0,
                "frames": 534,
                "holds": {},
                "jumps_rejected": 0,
                "malformed_frames": 0,
                "reanchors": 1,
                "tracking_losses": 0,
                "untracked_frames": 0,
            }
        },
        "overruns": 0,
        "processes": {},
        "qpos_sha256": "4db3c94bdd7c92265628fa6ddc0a33f01a5f2fb5ae37567dd02314cd8068f463",
        "rejected_by_reason": {},
        "success": True,
        "task": "PickupBox",
        "ticks": 269,
    },
    "PickupBox/rx1": {
        "commands_applied": 382,
        "commands_sha256": "5e7182bb5045c66870a04a793db3a4b13d26475f7770f9400df56c3cf22e7ec7",
        "duration_s": 8.0,
        "embodiment": "rx1",
        "frames_received": 952,
        "frames_rejected": 0,
        "frames_superseded": 0,
        "guard_blocks": {"left": 49, "right": 49},
        "hardware": {},
        "holds": {"left": {"guard": 49}, "right": {"guard": 49}},
        "latency_ms": {"n": 380},
        "listener_errors": {},
        "missed_ticks": 0,
        "operator": {
            "left": {
                "errors": 0,
                "frames": 476,
                "holds": {},
                "jumps_rejected": 0,
                "malformed_frames": 0,
                "reanchors": 1,
                "tracking_losses": 0,
                "untracked_frames": 0,
            },
            "right": {
                "errors": 0,
                "frames": 476,
                "holds": {},
                "jumps_rejected": 0,
                "malformed_frames": 0,
                "reanchors": 1,
                "tracking_losses": 0,
                "untracked_frames": 0,
            },
        },
        "overruns": 0,
        "processes": {},
        "qpos_sha256": "909fb2fc321ae6169aee439c7cc0bab776e72466c694081eb5b634e2c5e6d193",
        "rejected_by_reason": {},
        "success": True,
        "task": "PickupBox",
        "ticks": 240,
    },
}


def replay(task: str, embodiment: str | None, clock: str | None = None):
    """One process on a trace: the digest of every tick's commands (:func:`command_digest`),
    the summary and the final qpos."""
    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="trace",
        clock=clock,
        viser=False,
        headless=True,
        progress=False,
    )
    loop = build_loop(options)
    digest = hashlib.sha256()
    loop.listeners.append(lambda tick: digest.update(command_digest(tick.commands)))
    summary = loop.run()
    q = loop.twin.env.data.qpos.copy()
    loop.twin.env.close()
    return digest.hexdigest(), summary, q


def replay_digest(task: str, embodiment: str | None, clock: str | None = None) -> dict:
    commands, summary, q = replay(task, embodiment, clock)
    summary = summary.to_dict()
    summary.pop("loop_rate_hz")
    summary["latency_ms"] = {"n": summary["latency_ms"]["n"]}
    summary["commands_sha256"] = commands
    summary["qpos_sha256"] = hashlib.sha256(q.tobytes()).hexdigest()
    return summary


@pytest.mark.parametrize("key", sorted(EXPECTED))
def test_bundled_trace_replays_to_mains_summary_on_the_stages(key):
    task, embodiment = key.split("/")
    got = replay_digest(task, None if embodiment == "None" else embodiment)
    expected = EXPECTED[key]
    assert {k: got.get(k) for k in expected} == expected


# ------------------------------------------------------------------ both layouts
def command_digest(commands) -> bytes:
    """The bytes of one tick's commands (effector order): positions, hold, reason."""
    out = b""
    for name in sorted(commands):
        c = commands[name]
        out += name.encode() + np.asarray(c.positions, dtype=np.float64).tobytes()
        out += bytes([c.hold]) + c.reason.encode()
    return out


def digest_commands(process, path: str):
    """An attachment (``Attachment("test_stages:digest_commands", path)``): in the twin
    process, the digest of every lockstep tick's commands, written to ``path`` at the end."""
    digest = hashlib.sha256()
    ticks = [0]

    def after_step(state) -> None:
        digest.update(command_digest(process.tick_commands))
        ticks[0] += 1

    process.stage.after_step.append(after_step)

    def finish() -> None:
        with open(path, "w") as f:
            f.write(f"{digest.hexdigest()} {ticks[0]}")

    return finish


def one_process_digest(task: str, embodiment: str | None, clock: str):
    commands, summary, _ = replay(task, embodiment, clock)
    return commands, summary


def multiprocess_digest(task: str, embodiment: str | None, clock: str, tmp_path):
    from beavr_sim.teleop.process_config import Attachment
    from beavr_sim.teleop.processes import MultiprocessSession
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="trace",
        clock=clock,
        viser=False,
        headless=True,
        progress=False,
        multiprocess=True,
        transport=TransportConfig(ports=PortConfig.free()),
    )
    path = tmp_path / f"digest-{clock}-{embodiment}.txt"
    session = MultiprocessSession(
        options, attach=(Attachment(f"{__name__}:digest_commands", str(path)),)
    )
    summary = session.run(options.max_seconds, stop_on_success=True)
    digest, ticks = path.read_text().split()
    return digest, int(ticks), summary


@pytest.mark.parametrize(
    ("embodiment", "clock"), [(None, "virtual"), (None, "paced"), ("rx1", "virtual")]
)
def test_multiprocess_replays_a_trace_to_the_same_commands_as_one_process(
    embodiment, clock, tmp_path
):
    """The runner-equivalence test: a bundled trace through both layouts on the virtual and
    paced clocks gives the same commands, bit for bit (main refuses --clock paced with
    --multiprocess and runs --clock virtual on the real clock)."""
    expected, one = one_process_digest("PickupBox", embodiment, clock)
    digest, ticks, multi = multiprocess_digest("PickupBox", embodiment, clock, tmp_path)
    assert multi.processes == {"twin": "ok", "operator": "ok"}
    assert (digest, ticks) == (expected, one.ticks)
    for field in ("success", "frames_received", "commands_applied", "ticks", "holds"):
        assert getattr(multi, field) == getattr(one, field), field
    assert multi.latency_ms["n"] == one.latency_ms["n"]


# ------------------------------------------------------------------ the feature matrix
SOURCES = ("quest", "webxr", "trace")
CLOCKS = (None, "real", "virtual", "paced")
FEATURES = (
    "plain",
    "mirror",
    "view",
    "estop_inputs",
    "record",
    "rerun",
    "headset_images",
    "sync_timeout",
    "emulate_faults",
    "camera",
    "camera_stream",
    "camera_poses",
    "repeat",
)
#: ``--camera-poses``: a twin camera placed 1.5 m in front of the world origin, looking back.
CAMERA_POSES = """
[cameras.placed]
type = "opencv"
index_or_path = 0
fovy_deg = 60.0
T_world_camera = [[0, 0, -1, 1.5], [-1, 0, 0, 0], [0, 1, 0, 1.0], [0, 0, 0, 1]]
"""
MIRRORED_FEATURES = ("mirror", "estop_inputs", "sync_timeout", "emulate_faults")


def matrix_options(source, clock, feature, multiprocess, tmp_path) -> dict:
    kwargs = dict(
        task="PickupBox",
        source=source,
        clock=clock,
        viser=feature in ("view", "estop_inputs"),
        headless=feature != "headset_images",
        progress=False,
        multiprocess=multiprocess,
    )
    if feature in MIRRORED_FEATURES:  # e-stop: keys, button, gesture
        kwargs.update(mirror_hardware=True, hardware_config="emulated")
    if feature == "sync_timeout":
        kwargs["sync_timeout_s"] = 5.0
    if feature == "emulate_faults":
        kwargs["emulate_faults"] = "right_hand:freeze=2@3"
    if feature == "record":
        kwargs["record"] = tmp_path / "dataset"
    if feature == "rerun":
        kwargs["rerun"] = tmp_path / "session.rrd"
    if feature == "camera":  # a real camera (parsed, never opened here) records with --record
        kwargs.update(real_cameras=("wrist=opencv:0",), record=tmp_path / "dataset")
    if feature == "camera_stream":
        kwargs["camera_stream_hz"] = 5.0
    if feature == "camera_poses":
        poses = tmp_path / "poses.toml"
        poses.write_text(CAMERA_POSES)
        kwargs["camera_poses"] = poses
    if feature == "repeat":
        kwargs["repeat"] = 2
    return kwargs


def refusals(source, clock, feature, multiprocess) -> tuple[str, ...]:
    """What the combination is refused for (words one of which the error names; any one
    applies); empty: it must work."""
    reasons = []
    if feature in MIRRORED_FEATURES and clock == "virtual":
        reasons.append("real control rate")
    if clock in ("virtual", "paced") and source != "trace":
        reasons.append("recorded source")
    if feature == "repeat" and source != "trace":
        reasons.append("--source trace")
    return tuple(reasons)


@pytest.mark.parametrize("multiprocess", [False, True], ids=["one_process", "multiprocess"])
def test_every_source_clock_and_feature_works_in_both_layouts_or_is_refused(multiprocess, tmp_path):
    """Each combination of source x clock x feature is either refused with a one-line
    reason or carried into what the layout runs (the processes' configs): never silently
    ignored. Main refuses --clock paced and --source webxr with --multiprocess and runs
    --clock virtual there on the real clock."""
    from beavr_sim.teleop.processes import process_configs

    wrong = []
    for source, clock, feature in itertools.product(SOURCES, CLOCKS, FEATURES):
        case = f"{source} x {clock} x {feature}"
        expected = refusals(source, clock, feature, multiprocess)
        try:
            options = SessionOptions(
                **matrix_options(source, clock, feature, multiprocess, tmp_path)
            )
        except ValueError as exc:
            message = str(exc)
            if not any(word in message for word in expected) or "\n" in message:
                wrong.append(f"{case}: refused ({message})")
            continue
        if expected:
            wrong.append(f"{case}: accepted, expected a refusal naming one of {expected}")
            continue
        if not multiprocess:
            continue  # the single-process session is the reference
        op, twin = process_configs(options)
        carried = {
            "source": op.source == source and (op.webxr is not None) == (source == "webxr"),
            "clock": (twin.lockstep, twin.paced)
            == (options.clock in ("virtual", "paced"), options.clock == "paced"),
            "mirror": twin.mirror_hardware == (feature in MIRRORED_FEATURES),
            "sync_timeout": twin.sync_timeout_s == options.sync_timeout_s,
            "emulate_faults": twin.emulate_faults == options.emulate_faults,
            "rig": twin.hardware_config == options.hardware_config,
            "view": (twin.view is not None) == (feature in ("view", "estop_inputs")),
            "headset_images": (twin.headset_images is not None)
            == (feature == "headset_images" and source == "quest"),
            "page_twin": op.page_twin
            == (twin.page_twin is not None)
            == (feature == "headset_images" and source == "webxr")
            and (
                twin.page_twin is None
                or twin.page_twin.rate_hz == options.webxr_config().twin_rate_hz
            ),
            "control_rate": op.stage.control_hz == twin.control_hz,
            "record": (twin.recording is not None) == (feature in ("record", "camera"))
            and (twin.recording is None or twin.recording.auto_start == options.auto_start),
            "record_gesture": op.records == (twin.recording is not None),
            "camera_stream": (twin.camera_stream is not None) == (feature == "camera_stream"),
            "camera_page": op.camera_panels == (feature == "camera_stream" and source == "webxr"),
            "camera_poses": twin.placed_cameras == options.placed_cameras
            and bool(twin.placed_cameras) == (feature == "camera_poses"),
            "camera": (twin.recording.real_cameras if twin.recording else ())
            == options.real_cameras,
            "keypoints": op.keypoints == (feature in ("record", "camera", "rerun")),
            "rerun": (twin.rerun is not None) == (feature == "rerun"),
            "repeat": twin.plan.repeat == options.repeat
            and twin.ends_runs >= (feature == "repeat"),
        }
        wrong += [f"{case}: {what} not carried" for what, ok in carried.items() if not ok]
    assert not wrong, "\n".join(wrong)


# ------------------------------------------------------------------ the e-stop gesture
def pinching_trace(path, t_pinch: float = 1.0):
    """The bundled RX-1 PickupBox trace with both hands pinching from ``t_pinch`` on."""
    from beavr_sim.assets import bundled_trace
    from beavr_sim.traces.format import TraceReader, TraceWriter

    reader = TraceReader(bundled_trace("PickupBox", "rx1"))
    with TraceWriter(path, reader.metadata) as writer:
        for _t, kind, payload in reader.events():
            if kind == "hand":
                writer.write_hand(dataclasses.replace(payload, pinch=payload.t_source >= t_pinch))
    return path


@pytest.mark.parametrize(
    ("multiprocess", "clock"),
    [(False, None), (True, None), (True, "paced")],
    ids=["one_process", "multiprocess", "multiprocess_paced"],
)
def test_both_hands_pinching_latches_the_estop_on_every_mirrored_device(
    multiprocess, clock, tmp_path
):
    """The headset's e-stop gesture reaches the mirror in both layouts, on the real clock
    and in lockstep (main's --multiprocess never forwarded it: the devices went on moving)."""
    from beavr_sim.teleop.session import run_session
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    options = SessionOptions(
        task="PickupBox",
        embodiment="rx1",
        source="trace",
        trace=pinching_trace(tmp_path / "pinch.mcap"),
        viser=False,
        headless=True,
        progress=False,
        multiprocess=multiprocess,
        clock=clock,
        mirror_hardware=True,
        hardware_config="emulated",
        max_seconds=3.0,
        transport=TransportConfig(ports=PortConfig.free()),
    )
    summary = run_session(options)
    assert summary.hardware, summary
    for name, device in summary.hardware.items():
        assert "headset gesture" in device["holding"], (name, device)


# ------------------------------------------------------------------ the twin process's rules
def test_an_ik_infeasible_hold_moves_the_fingers_in_the_twin_process_as_in_one():
    """The operator's ``ik_infeasible`` hold keeps the arm and moves the fingers: the twin
    process applies its positions as one process does (main's twin_main skipped every hold,
    fingers included); a hold without positions keeps the last targets."""
    from beavr_sim.teleop.process_config import command_from_wire
    from beavr_sim.wire.messages import JointCommandMsg

    positions = [0.1 * i for i in range(23)]
    msg = JointCommandMsg(
        effector="right",
        t_source=1.5,
        t_command=1.6,
        positions=positions,
        hold=True,
        reason="ik_infeasible",
    )
    cmd = command_from_wire(msg)
    assert cmd is not None and cmd.hold and cmd.reason == "ik_infeasible"
    np.testing.assert_array_equal(cmd.positions, positions)
    empty = JointCommandMsg(effector="right", t_source=0.0, t_command=1.6, positions=[], hold=True)
    assert command_from_wire(empty) is None
    held = np.arange(23.0)
    np.testing.assert_array_equal(command_from_wire(empty, held=held).positions, held)


def test_the_twin_stage_counts_latency_per_command_and_isolates_its_hooks():
    """Every accepted command counts (main's twin process counted only distinct t_source
    values); a hook that raises is counted, the stage goes on."""
    import gymnasium as gym

    from beavr_sim.teleop.stages import TwinStage
    from beavr_sim.twin.twin import TwinInterface
    from beavr_sim.wire.records import JointCommand

    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    try:
        twin = TwinInterface(env)
        q = twin.reset(0)
        stage = TwinStage(twin)
        seen = []

        def broken(outcome, commands):
            raise RuntimeError("a viewer bug")

        stage.after_command += [lambda outcome, commands: seen.append(outcome), broken]
        t = time.monotonic()
        same = JointCommand("right", q[twin.slices["right"]].copy(), t, t)
        for _ in range(3):  # one hand frame's command, applied three times
            outcome = stage.command({"right": same})
            assert outcome.accepted == ("right",)
        stage.step()
        assert len(stage.latencies_ms) == 3 and len(seen) == 3
        assert stage.hook_errors == {"broken": 3}
    finally:
        env.close()


# ------------------------------------------------------------------ WebXR across processes
def next_page_message(ws, kind: str, deadline: float) -> dict:
    """The next message of ``kind`` the page gets (others skipped), before ``deadline``."""
    import json

    while (remaining := deadline - time.monotonic()) > 0:
        try:
            message = json.loads(ws.recv(timeout=remaining))
        except TimeoutError:
            break
        if message["type"] == kind:
            return message
    raise AssertionError(f"no {kind!r} message came to the page")


def test_a_webxr_page_drives_a_multiprocess_session_sees_its_twin_and_its_pinch_latches_every_device():
    """--source webxr --multiprocess without --headless (main refused both): the operator
    process hosts the page server; a raw WebSocket client gets the twin's scene and poses
    from the twin process, sends both hands moving (the poses follow the twin), then both
    pinch: every emulated device latches the e-stop (the twin's state, and the page's twin
    message, say the operator holds paused)."""
    from websockets.sync.client import connect

    from beavr_sim.headset.layouts import LAYOUTS
    from beavr_sim.headset.webxr_protocol import encode_hands
    from beavr_sim.teleop.processes import MultiprocessSession
    from beavr_sim.wire.hand import N_JOINTS
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    options = SessionOptions(
        task="PickupBox",
        embodiment="rx1",
        source="webxr",
        seed=0,  # the twin's reset once the rig is in sync places the box where it was
        viser=False,
        headless=False,
        progress=False,
        multiprocess=True,
        mirror_hardware=True,
        hardware_config="emulated",
        transport=TransportConfig(ports=PortConfig.free()),
    )
    rng = np.random.default_rng(0)
    canonical = np.array([0.3, 0.0, 1.1]) + rng.uniform(-0.09, 0.09, size=(N_JOINTS, 3))
    session = MultiprocessSession(options)
    session.start()  # returns once both processes are ready: the page server is up
    try:
        url = f"ws://127.0.0.1:{options.webxr_config().port}/ws"
        t_ms = 1.7e12
        deadline = time.monotonic() + 120.0
        with connect(url) as ws:
            assert next_page_message(ws, "welcome", deadline)["server"] == "beavr_sim"
            scene = next_page_message(ws, "scene", deadline)
            assert scene["embodiment"] == "rx1" and scene["meshes"]
            rest = next_page_message(ws, "twin", deadline)
            assert len(rest["pose"]) == 12 * len(scene["dynamic"]) and not rest["paused"]
            for i in range(40):  # 20 frames moving the hands 8 cm forward, then both pinch
                shift = np.array([0.004 * min(i, 20), 0.0, 0.0])
                hand = LAYOUTS["webxr25"].from_canonical(canonical + shift)
                pinch = {"left": i >= 20, "right": i >= 20}
                hands = {"left": hand, "right": hand}
                ws.send(encode_hands(t_ms + 33 * i, hands, seq=i, pinch=pinch))
                if i == 19:  # the page's poses follow the twin's motion
                    moved = rest
                    while np.abs(np.subtract(moved["pose"], rest["pose"])).max() < 0.01:
                        moved = next_page_message(ws, "twin", deadline)
            while time.monotonic() < deadline:  # the twin's states say when it latched
                state = session.state_sub.recv_latest(0.5)
                if state is not None and state.paused:
                    break
            else:
                raise AssertionError("the mirror never latched its e-stop")
            while not next_page_message(ws, "twin", deadline)["paused"]:
                pass  # the page's twin says the operator holds paused
    finally:
        session.stop()
    op, twin = session.results["operator"], session.results["twin"]
    assert op["detector"]["frames_received"] == 80 and op["estop_events"] == 1
    assert op["page_twin"]["poses_sent"] > 0 and op["page_twin"]["bad_scenes"] == 0
    for name, device in twin["hardware"].items():
        assert "headset gesture" in device["holding"], (name, device)
