"""Real-camera support through LeRobot's camera classes, with no camera attached: an OpenCV
camera reading a generated video file and a ZMQ camera fed by a test image server on 127.0.0.1."""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from fixtures_shared import FrameSink, ImageServer
from lerobot.cameras.opencv.configuration_opencv import OpenCVCameraConfig
from lerobot.cameras.zmq.configuration_zmq import ZMQCameraConfig

from beavr_sim.cameras.errors import CameraError, CameraSpecError
from beavr_sim.cameras.real import RealCameras
from beavr_sim.cameras.spec import merge_cameras, parse_camera_arg, parse_camera_table

WAIT_S = 20.0  # generous readiness deadline, never a pass/fail timing bound


def _wait_for(predicate, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


@pytest.fixture
def server():
    srv = ImageServer()
    yield srv
    srv.close()


def _zmq_set(port: int, period_s: float = 0.05, dead_after_s: float = 1.0) -> RealCameras:
    config = parse_camera_table(
        "front",
        {
            "type": "zmq",
            "server_address": "127.0.0.1",
            "port": port,
            "warmup_s": 0,
            "timeout_ms": 200,
        },
    )
    return RealCameras({"front": config}, control_period_s=period_s, dead_after_s=dead_after_s)


def _video(path: Path, frames: int) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (32, 24))
    for i in range(frames):
        writer.write(np.full((24, 32, 3), i % 250, np.uint8))
    writer.release()
    return path


# --- specs -----------------------------------------------------------------------------------


def test_cli_specs_become_lerobot_configs():
    name, cfg = parse_camera_arg("wrist=opencv:0@640x480")
    assert name == "wrist" and isinstance(cfg, OpenCVCameraConfig)
    assert (cfg.index_or_path, cfg.width, cfg.height, cfg.fps) == (0, 640, 480, 30)
    _, cfg = parse_camera_arg("top=opencv:/tmp/x.avi")
    assert cfg.index_or_path == Path("/tmp/x.avi") and cfg.width is None
    assert cfg.fps is None  # a video file plays at its own rate
    _, cfg = parse_camera_arg("top=zmq:10.0.0.2:5555")
    assert isinstance(cfg, ZMQCameraConfig) and (cfg.server_address, cfg.port) == ("10.0.0.2", 5555)
    assert (cfg.camera_name, cfg.warmup_s, cfg.timeout_ms) == ("top", 0, 1000)
    _, cfg = parse_camera_arg("d=realsense:1234@640x480")
    assert cfg.serial_number_or_name == "1234" and not cfg.use_depth


def test_depth_on_the_command_line_is_the_rig_tables_use_depth():
    """``realsense:SERIAL@WxH+depth`` is the very config of a rig table's ``use_depth = true``;
    depth on a type without it is one line naming the camera and the types with depth."""
    name, cli = parse_camera_arg("wrist=realsense:123456789@640x480+depth", fps=15)
    table = {"type": "intelrealsense", "serial_number_or_name": "123456789", "use_depth": True}
    rig = parse_camera_table("wrist", {**table, "width": 640, "height": 480, "fps": 15})
    assert name == "wrist" and cli == rig and cli.use_depth
    no_depth = r"camera 'w': type '{}' has no depth .*types with depth: intelrealsense, realsense$"
    for arg, kind in (("w=opencv:0@64x48+depth", "opencv"), ("w=zmq:h:5555+depth", "zmq")):
        with pytest.raises(CameraSpecError, match=no_depth.format(kind)) as info:
            parse_camera_arg(arg)
        assert "\n" not in str(info.value)
    with pytest.raises(CameraSpecError, match=no_depth.format("opencv")):
        parse_camera_table("w", {"type": "opencv", "index_or_path": 0, "use_depth": True})
    with pytest.raises(CameraSpecError, match=r"'w': a realsense spec needs its size: .*@WIDTH"):
        parse_camera_arg("w=realsense:1+depth")
    with pytest.raises(CameraSpecError, match=r"'w': \+depth goes last"):
        parse_camera_arg("w=realsense:1+depth@64x48")


@pytest.mark.parametrize(
    "arg, fragment",
    [
        ("front", "NAME=SPEC"),
        ("front=usb:0", "opencv:INDEX_OR_PATH"),
        ("front=opencv:0@640", "WIDTHxHEIGHT"),
        ("front=zmq:host", "HOST:PORT"),
        ("fr-ont=opencv:0", "letters"),
    ],
)
def test_cli_spec_errors_name_the_camera_and_the_choices(arg, fragment):
    with pytest.raises(CameraSpecError, match=fragment) as info:
        parse_camera_arg(arg)
    assert "\n" not in str(info.value)


def test_rig_table_errors_list_valid_choices():
    with pytest.raises(CameraSpecError, match=r"'front'.*not one of \['intelrealsense', 'opencv'"):
        parse_camera_table("front", {"type": "usb"})
    with pytest.raises(
        CameraSpecError, match=r"unknown keys \['exposur'\].*valid: .*index_or_path"
    ):
        parse_camera_table("front", {"type": "opencv", "index_or_path": 0, "exposur": 3})
    with pytest.raises(CameraSpecError, match="'front'"):
        parse_camera_table("front", {"type": "opencv"})
    with pytest.raises(CameraSpecError, match="both in the rig file and by --camera"):
        merge_cameras(
            {"front": parse_camera_table("front", {"type": "opencv", "index_or_path": 0})},
            dict([parse_camera_arg("front=opencv:1")]),
        )


def test_a_cameras_name_is_recorded_as_given_and_case_only_twins_are_refused():
    """``--camera Front=...`` records ``observation.images.Front`` (never lowercased); names
    that differ only in case would share a folder on macOS / Windows: one line naming both."""
    from beavr_sim.datasets.features import RecordingConfig, lerobot_features
    from beavr_sim.robots import make_embodiment

    name, _ = parse_camera_arg("Front=opencv:0@64x48")
    assert name == "Front"
    table = {"Front": parse_camera_table("Front", {"type": "opencv", "index_or_path": 0})}
    assert list(merge_cameras(table, {})) == ["Front"]
    rx1, config = make_embodiment("rx1"), RecordingConfig(cameras=("overhead",))
    features = lerobot_features(rx1, config, real_cameras={"Front": (48, 64, 3)})
    assert "observation.images.Front" in features and "observation.images.front" not in features
    with pytest.raises(ValueError, match=r"'Front' and 'front' differ only in case") as info:
        lerobot_features(
            rx1, RecordingConfig(cameras=("front",)), real_cameras={"Front": (48, 64, 3)}
        )
    assert "\n" not in str(info.value)
    with pytest.raises(CameraSpecError, match=r"'FRONT' \(--camera\) and 'Front' \(rig file\)"):
        merge_cameras(table, dict([parse_camera_arg("FRONT=opencv:1")]))


def test_unreachable_camera_fails_at_start_with_what_to_check(tmp_path):
    _, cfg = parse_camera_arg(f"front=opencv:{tmp_path / 'missing.avi'}")
    cams = RealCameras({"front": cfg}, control_period_s=0.05)
    with pytest.raises(
        CameraError, match=r"camera 'front' \(opencv\) failed to start: .*check that .*missing.avi"
    ):
        cams.connect()


# --- capture through LeRobot's cameras -------------------------------------------------------


def test_opencv_video_file_delivers_then_dies_at_end(tmp_path, caplog):
    cfg = parse_camera_table(
        "front",
        {
            "type": "opencv",
            "fps": None,
            "warmup_s": 0,
            "index_or_path": str(_video(tmp_path / "v.avi", 300)),
        },
    )
    cams = RealCameras({"front": cfg}, control_period_s=0.05, dead_after_s=0.5)
    cams.connect()
    try:
        assert cams.frame_shape("front") == (24, 32, 3)
        # The file ends, LeRobot's read thread gives up: the camera is reported dead, no frame.
        _wait_for(lambda: cams.grab().dead == ("front",), "the video's end to be reported dead")
        assert "front" not in cams.grab().frames
        # LeRobot's read thread raised: one log line, not a thread traceback on stderr
        _wait_for(lambda: any("camera stopped" in r.message for r in caplog.records), "the line")
        (line,) = [r.message for r in caplog.records if "camera stopped" in r.message]
        assert "OpenCVCamera(" in line and "\n" not in line, line
    finally:
        cams.close()


def test_zmq_frames_are_the_newest_and_live(server):
    cams = _zmq_set(server.port)
    cams.connect()
    try:
        stamps = []
        for _ in range(5):
            sent = server.sent
            _wait_for(lambda sent=sent: server.sent >= sent + 3, "the server to publish")
            grab = cams.grab()
            assert grab.dead == () and grab.frames["front"].shape == (24, 32, 3)
            stamps.append(cams._last_stamp["front"])
        assert len(set(stamps)) >= 4  # newest frame each time, not a frozen one
        summary = cams.summary()["front"]
        assert summary["frames"] == 5 and summary["repeats"] <= 1
    finally:
        cams.close()


def test_stale_frames_are_counted_against_the_control_period(server):
    fast = _zmq_set(server.port, period_s=1e-7)  # 1.5 periods is far below any real capture age
    fast.connect()
    try:
        for _ in range(3):
            fast.grab()
        assert fast.summary()["front"]["stale"] == 3
        fast.start_episode()
        assert fast.summary()["front"]["stale"] == 0
    finally:
        fast.close()
    slow = _zmq_set(server.port, period_s=100.0)
    slow.connect()
    try:
        for _ in range(3):
            slow.grab()
        assert slow.summary()["front"]["stale"] == 0
    finally:
        slow.close()


def test_camera_dying_mid_episode_is_reported_dead(server):
    cams = _zmq_set(server.port, dead_after_s=0.3)
    cams.connect()
    try:
        assert cams.grab().dead == ()
        server.stop.set()
        _wait_for(lambda: cams.grab().dead == ("front",), "the silent camera to be reported dead")
    finally:
        cams.close()


# --- recorded sessions -----------------------------------------------------------------------


def _record(
    tmp_path,
    port: int,
    episode_s: float,
    listener=None,
    stream_hz=0.0,
    viewers=None,
    twin=False,
    multiprocess: bool = False,
):
    from dataclasses import replace

    from beavr_sim.datasets.features import RecordingConfig
    from beavr_sim.teleop.session import (
        ProgressLine,
        SessionOptions,
        build_loop,
        record_episodes,
        run_session,
        twin_camera_panels,
    )
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    options = SessionOptions(
        task="PickupBox",
        source="trace",
        clock="paced",
        viser=False,
        headless=True,
        progress=False,
        record=tmp_path / "rec",
        repo_id="local/cams",
        episodes=1,
        recording=RecordingConfig(cameras=(), episode_seconds=episode_s, use_videos=False),
        auto_start=True,
        real_cameras=(f"front=zmq:127.0.0.1:{port}",),
        camera_stream_hz=stream_hz,
        multiprocess=multiprocess,
        transport=TransportConfig(ports=PortConfig.free()),
    )
    if multiprocess:  # the real camera read in the twin process, next to its recorder
        run_session(options)
    else:
        loop = build_loop(options)
        if listener is not None:
            loop.listeners.append(listener)
        if twin:  # the twin's renders of the camera, as run_session adds them when streaming
            viewers = replace(viewers, **twin_camera_panels(options, loop))
        record_episodes(options, loop, ProgressLine(loop, enabled=False), viewers=viewers)
    lines = (tmp_path / "rec" / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    return [json.loads(x) for x in lines]


@pytest.mark.parametrize("multiprocess", [False, True], ids=["one_process", "multiprocess"])
def test_recorded_frames_are_live_camera_frames(tmp_path, server, multiprocess):
    """In both layouts (main refused --camera with --multiprocess)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    (record,) = _record(tmp_path, server.port, episode_s=1.0, multiprocess=multiprocess)
    assert record["kept"] and record["hardware_fault"] is None
    cams = record["cameras"]["front"]
    assert cams["frames"] >= record["frames"] and cams["repeats"] < cams["frames"] / 2
    assert "stale" in cams and "age_p99_ms" in cams
    ds = LeRobotDataset("local/cams", root=tmp_path / "rec")
    assert ds.features["observation.images.front"]["shape"] == (24, 32, 3)
    levels = {
        round(float(ds[i]["observation.images.front"].mean()), 3) for i in range(ds.num_frames)
    }
    assert len(levels) > ds.num_frames / 2  # the server's frames move on: not a frozen image


def test_camera_dying_mid_episode_ends_it_as_a_hardware_fault(tmp_path, server):
    ticks = []

    def stop_camera(tick):
        ticks.append(tick)
        if len(ticks) == 10:
            server.stop.set()

    records = _record(tmp_path, server.port, episode_s=30.0, listener=stop_camera)
    assert not any(r["kept"] for r in records)  # a trace's spoilt episode is retried, never saved
    record = records[0]
    assert not record["success"]
    assert record["hardware_fault"] == "camera front stopped delivering frames"
    assert record["ended_by"] == "hardware_fault"
    assert record["frames"] < 30 * 30  # ended at the fault, not at the time limit


def test_camera_flag_errors():
    from beavr_sim.teleop.session import SessionOptions

    with pytest.raises(ValueError, match="add --record or --camera-stream-hz"):
        SessionOptions(
            task="PickupBox",
            source="trace",
            viser=False,
            headless=True,
            real_cameras=("front=opencv:0",),
        )
    streams = SessionOptions(  # without --record: the twin's cameras are streamed
        task="PickupBox", source="trace", viser=False, headless=True, camera_stream_hz=5.0
    )
    assert streams.camera_stream_config().view == "auto"
    streams = SessionOptions(  # --multiprocess: streamed from the twin process
        task="PickupBox", source="trace", headless=True, multiprocess=True, camera_stream_hz=5.0
    )
    assert streams.multiprocess and streams.camera_stream_hz == 5.0
    with pytest.raises(ValueError, match="real, twin, both, overlay"):
        SessionOptions(
            task="PickupBox", source="trace", viser=False, headless=True, camera_view="side"
        )
    with pytest.raises(CameraSpecError, match="opencv:INDEX_OR_PATH"):
        SessionOptions(
            task="PickupBox",
            source="trace",
            viser=False,
            headless=True,
            record=Path("x"),
            real_cameras=("front=usb:0",),
        )


def test_stream_reads_a_live_zmq_camera_and_shows_no_signal_once_it_dies(server):
    from beavr_sim.cameras.stream import LIVE, NO_SIGNAL, CameraStream, StreamConfig

    cams = _zmq_set(server.port, dead_after_s=0.3)
    cams.connect()
    panels = []
    stream = CameraStream(
        StreamConfig(rate_hz=50.0, dead_after_s=0.3),
        [panels.append],
        {"front": cams.frame_shape("front")},
        source=cams.peek,
    )
    try:
        _wait_for(lambda: any(p.state == LIVE for p in panels), "a live panel")
        assert cams.stats["front"].frames == 0  # the viewer's reads count nothing
        server.stop.set()  # the camera stops delivering
        _wait_for(lambda: panels[-1].state == NO_SIGNAL, "the panel to read NO SIGNAL")
        assert panels[-1].age_s is None
    finally:
        stream.close()
        cams.close()


class _View:  # the browser view's part the stream uses
    def __init__(self, shapes=None) -> None:
        self.shapes = shapes
        self.panels = []
        self.arrived = threading.Event()
        self.panel = None

    def add_camera_panel(self, shapes):
        assert self.shapes is None or shapes == self.shapes
        self.panel = _Panel(self)
        return self.panel

    def wait_until(self, predicate, n: int = 1):
        """A tick listener holding the control loop at tick ``n`` until a panel arrived that
        ``predicate`` accepts (readiness, never a timing bound: the first twin render makes
        its GL context)."""
        ticks = [0]

        def listener(tick) -> None:
            ticks[0] += 1
            if ticks[0] == n:
                _wait_for(lambda: any(predicate(p) for p in self.panels), "a panel")

        return listener


class _Panel:
    def __init__(self, view) -> None:
        self.view = view
        self.stream = None

    def attach(self, stream) -> None:
        self.stream = stream

    def __call__(self, frame) -> None:
        self.view.panels.append(frame)


def test_a_recording_session_streams_its_camera_to_the_viewers(tmp_path, server):
    from beavr_sim.teleop.camera_viewers import CameraViewers

    view = _View({"front": (24, 32, 3)})
    (record,) = _record(
        tmp_path, server.port, 1.0, stream_hz=20.0, viewers=CameraViewers(view=view)
    )
    assert record["kept"] and record["hardware_fault"] is None
    assert any(p.state == "live" and p.image.shape == (24, 32, 3) for p in view.panels)
    assert record["cameras"]["front"]["frames"] >= record["frames"]  # the recorder's own grabs


def test_a_recording_session_streams_the_real_camera_and_the_twin_side_by_side(tmp_path, server):
    from beavr_sim.teleop.camera_viewers import CameraViewers

    view = _View({"front": (24, 32, 3)})

    def both(p) -> bool:
        return p.state == "live" and p.image.shape == (24, 64, 3) and p.note == "twin"

    (record,) = _record(
        tmp_path, server.port, 1.0, listener=view.wait_until(both, 5), stream_hz=20.0,
        viewers=CameraViewers(view=view), twin=True,
    )  # fmt: skip
    assert record["kept"] and record["hardware_fault"] is None
    stream = view.panel.stream
    assert stream.view == "both"  # auto: the twin has a camera of the real camera's name
    panel = next(p for p in view.panels if both(p))
    real, twin = panel.image[:, :32].astype(float), panel.image[:, 32:].astype(float)
    assert real.std() < 3 and twin.std() > 10  # the server's flat grey | the twin's scene
    assert stream.twin_renders > 0 and stream.twin_errors == 0


def test_a_session_without_cameras_streams_the_twins_camera(monkeypatch):
    from dataclasses import replace

    from beavr_sim.teleop import session

    view = _View()
    started = []

    def start(real, config, viewers):  # the session's own viewers plus the test's browser view
        stream = real_start(real, config, replace(viewers, view=view))
        started.append(stream)
        return stream

    real_start = session.start_camera_stream
    monkeypatch.setattr(session, "start_camera_stream", start)
    options = session.SessionOptions(
        task="PickupBox", source="trace", clock="paced", viser=False, headless=True,
        progress=False, max_seconds=0.5, camera_stream_hz=20.0,
    )  # fmt: skip

    def live_twin(p) -> bool:
        return p.state == "live" and p.image.shape == (480, 640, 3)

    session.run_session(
        options, on_loop=lambda loop: loop.listeners.append(view.wait_until(live_twin, 3))
    )
    (stream,) = started
    assert not stream.running  # closed with the session
    assert {p.name for p in view.panels} == {"front"}  # no real camera: the twin's front
    assert stream.real == () and stream.twin_renders > 0 and stream.twin_errors == 0


def test_a_session_without_recording_streams_its_real_camera(monkeypatch, server):
    """``--camera front=zmq:... --camera-stream-hz`` without ``--record``: a camera watching
    a sim-only session, shown next to the twin's ``front``."""
    from dataclasses import replace

    from beavr_sim.teleop import session

    view = _View({"front": (24, 32, 3)})
    started = []

    def start(real, config, viewers):  # the session's own viewers plus the test's browser view
        started.append((real, real_start(real, config, replace(viewers, view=view))))
        return started[-1][1]

    real_start = session.start_camera_stream
    monkeypatch.setattr(session, "start_camera_stream", start)
    options = session.SessionOptions(
        task="PickupBox", source="trace", clock="paced", viser=False, headless=True,
        progress=False, max_seconds=0.5, camera_stream_hz=20.0,
        real_cameras=(f"front=zmq:127.0.0.1:{server.port}",),
    )  # fmt: skip

    def both(p) -> bool:
        return p.state == "live" and p.image.shape == (24, 64, 3) and p.note == "twin"

    session.run_session(
        options, on_loop=lambda loop: loop.listeners.append(view.wait_until(both, 3))
    )
    ((real, stream),) = started
    assert tuple(real.names) == ("front",)
    assert not stream.running and stream.view == "both"
    panel = next(p for p in view.panels if both(p))
    assert panel.image[:, :32].std() < 3 and panel.image[:, 32:].std() > 10  # real | twin
    assert real.stats["front"].frames == 0  # the stream's reads count nothing


def test_a_mirrored_rig_files_camera_is_recorded(tmp_path, server):
    """`[cameras.NAME]` in the rig file of a mirrored session (the emulated rig, its devices
    written into a rig file as a real rig's are) records that camera."""
    import gymnasium as gym

    from beavr_sim.datasets.features import RecordingConfig
    from beavr_sim.hardware.rig import EmulatedRig
    from beavr_sim.teleop.session import SessionOptions, run_session

    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    rig = EmulatedRig(env.embodiment, env.joints)
    env.close()
    try:
        lines = []
        for d in rig.config.devices:
            lines += ["[[devices]]", f'name = "{d.name}"', f'kind = "{d.kind}"']
            lines.append(f'effector = "{d.effector}"')
            if d.kind == "xarm7":
                lines += [f'host = "{d.config.host}"', f"port = {d.config.port}"]
            else:
                lines += [f'port = "{d.config.port}"', "reply_timeout_s = 0.25"]
        lines += ["[mirror]", "hand_divergence_rad = 2.5", "[cameras.front]", 'type = "zmq"']
        lines += ['server_address = "127.0.0.1"', f"port = {server.port}", "warmup_s = 0"]
        (tmp_path / "rig.toml").write_text("\n".join(lines) + "\n")
        run_session(
            SessionOptions(
                task="PickupBox",
                source="trace",
                clock="paced",
                viser=False,
                headless=True,
                progress=False,
                mirror_hardware=True,
                hardware_config=str(tmp_path / "rig.toml"),
                record=tmp_path / "rec",
                repo_id="local/rigcam",
                episodes=1,
                recording=RecordingConfig(cameras=(), episode_seconds=0.5, use_videos=False),
                auto_start=True,
            )
        )
    finally:
        rig.close()
    lines = (tmp_path / "rec" / "meta" / "beavr_episodes.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    # A busy machine can spoil a run (a device reply missed, a stale reading): that run is
    # a hardware fault, never kept, and the trace is played again.
    assert [r["kept"] for r in records] == [False] * (len(records) - 1) + [True], records
    assert all(r["hardware_fault"] for r in records[:-1]), records
    record = records[-1]
    assert record["hardware_fault"] is None
    assert record["cameras"]["front"]["frames"] >= record["frames"] > 0
    info = json.loads((tmp_path / "rec" / "meta" / "info.json").read_text())
    assert info["features"]["observation.images.front"]["shape"] == [24, 32, 3]


# --- the LeRobot robot's cameras (--robot.type=beavr_sim --robot.cameras) ---------------------


def _robot_config(cameras: dict, twin: tuple[str, ...] = (), **kwargs):
    from beavr_sim.integrations.config_robot import BeavrSimRobotConfig

    return BeavrSimRobotConfig(
        task="PickupBox", camera_names=list(twin), cameras=cameras, use_guard=False, **kwargs
    )


def _zmq_robot_camera(port: int) -> ZMQCameraConfig:
    return ZMQCameraConfig(
        server_address="127.0.0.1",
        port=port,
        camera_name="front",
        width=32,
        height=24,
        fps=30,
        timeout_ms=200,
    )


def test_robot_observation_has_the_real_cameras_newest_frames(server, tmp_path):
    from lerobot.utils.feature_utils import hw_to_dataset_features

    from beavr_sim.cameras.errors import CameraStoppedError
    from beavr_sim.integrations.robot import BeavrSimRobot

    robot = BeavrSimRobot(
        _robot_config(
            {"wrist": _zmq_robot_camera(server.port)},
            twin=("front",),  # the twin's front beside the real wrist camera
            camera_max_age_s=1.0,  # a busy machine's scheduling never reads as a dead camera
            calibration_dir=tmp_path,
            image_height=24,
            image_width=32,
        )
    )
    features = hw_to_dataset_features(robot.observation_features, "observation", use_video=True)
    assert features["observation.images.wrist"]["shape"] == (24, 32, 3)
    robot.connect()
    try:
        obs = robot.get_observation()
        assert obs["wrist"].shape == (24, 32, 3) and obs["front"].shape == (24, 32, 3)
        first = float(obs["wrist"].mean())
        sent = server.sent
        _wait_for(lambda: server.sent >= sent + 5, "the server to publish")
        _wait_for(lambda: float(robot.get_observation()["wrist"].mean()) != first, "a new frame")
        server.stop.set()  # the camera goes silent: no frozen frame is observed as live

        def raised() -> bool:
            try:
                robot.get_observation()
            except CameraStoppedError as exc:
                raised.message = str(exc)  # type: ignore[attr-defined]
                return True
            return False

        _wait_for(raised, "get_observation to refuse the silent camera")
        message = raised.message  # type: ignore[attr-defined]
        assert "camera 'wrist' stopped delivering frames (no frame for over 1 s)" in message
        assert "\n" not in message
    finally:
        robot.disconnect()
    assert robot.real_cameras is None


def test_robot_camera_that_does_not_open_or_ends_fails_in_one_line(tmp_path):
    from beavr_sim.cameras.errors import CameraStoppedError
    from beavr_sim.integrations.robot import BeavrSimRobot

    video = _video(tmp_path / "v.avi", 60)

    def opencv(path: Path, width: int = 32) -> OpenCVCameraConfig:
        return OpenCVCameraConfig(index_or_path=path, width=width, height=24, fps=30, warmup_s=0)

    robot = BeavrSimRobot(_robot_config({"wrist": opencv(tmp_path / "missing.avi")}))
    with pytest.raises(CameraError) as info:
        robot.connect()
    message = str(info.value)
    assert message.startswith("camera 'wrist' (opencv) failed to start: ") and "\n" not in message
    assert "check that " in message and "missing.avi" in message
    assert not robot.is_connected and robot.real_cameras is None
    robot = BeavrSimRobot(_robot_config({"wrist": opencv(video, width=64)}))
    with pytest.raises(CameraError, match=r"frames are width=32 x height=24, not the configured"):
        robot.connect()
    # The file's size as configured: it opens, plays (LeRobot reads a file as fast as it
    # decodes), ends; the robot then refuses to observe rather than repeat its last frame.
    robot = BeavrSimRobot(_robot_config({"wrist": opencv(video)}))
    robot.connect()
    try:
        with pytest.raises(CameraStoppedError, match=r"'wrist' .*its read thread ended"):
            _wait_for(lambda: robot.get_observation() is None, "the file's end")
    finally:
        robot.disconnect()


def test_robot_real_and_twin_camera_names_cannot_collide(tmp_path):
    """A twin camera with a real one's name is observed as NAME_twin (the real keeps NAME:
    what a policy trained on real data reads); a NAME_twin taken by another camera is refused."""
    from beavr_sim.integrations.robot import BeavrSimRobot

    real = OpenCVCameraConfig(index_or_path=0, width=32, height=24, fps=30)
    both = BeavrSimRobot(_robot_config({"front": real}, twin=("front",), image_height=48))
    assert both.observation_features["front"] == (24, 32, 3)
    assert both.observation_features["front_twin"] == (48, 640, 3)
    with pytest.raises(CameraSpecError) as info:
        _robot_config({"front": real, "front_twin": real}, twin=("front",))
    message = str(info.value)
    assert "twin camera 'front' is recorded as 'front_twin' (a real camera is 'front'), but " in (
        message
    )
    assert "\n" not in message
    with pytest.raises(CameraSpecError, match=r"camera 'wrist': give width, height"):
        _robot_config({"wrist": OpenCVCameraConfig(index_or_path=0)})
    # A rig file's [cameras.NAME] tables are the robot's real cameras too (hardware = the rig).
    rig = tmp_path / "rig.toml"
    rig.write_text('[cameras.overhead]\ntype = "zmq"\nserver_address = "127.0.0.1"\nwidth = 32\n')
    with pytest.raises(CameraSpecError, match=r"camera 'overhead': give height"):
        _robot_config({}, hardware=str(rig))
    rig.write_text(rig.read_text() + "height = 24\n")
    robot = BeavrSimRobot(_robot_config({"wrist": real}, hardware=str(rig)))
    assert robot.observation_features["overhead"] == (24, 32, 3)
    assert robot.observation_features["wrist"] == (24, 32, 3)
    with pytest.raises(
        CameraSpecError, match=r"'overhead' is named both in the rig file and by cameras"
    ):
        _robot_config({"overhead": real}, hardware=str(rig))
    twin = BeavrSimRobot(_robot_config({}, twin=("overhead",), hardware=str(rig)))
    assert {"overhead", "overhead_twin"} <= set(twin.observation_features)


def test_robot_stands_its_twin_camera_at_a_rig_files_pose_beside_the_real_one(server, tmp_path):
    """``camera_poses`` (a rig file, teleop's loader) moves the twin's ``front`` to the real
    ``front``'s ``T_world_camera``; the observation has the real frame as ``front`` and the
    twin's render from that pose as ``front_twin``."""
    import mujoco

    from beavr_sim.envs.camera_pose import PlacedCamera
    from beavr_sim.integrations.robot import BeavrSimRobot

    # 1.45 m in front of the base, 1.35 m up, looking back at the robot and 30 deg down.
    T = [[0.0, 0.5, -0.866025, 1.45], [1.0, 0.0, 0.0, 0.0], [0.0, -0.866025, -0.5, 1.35]]
    rig = tmp_path / "rig.toml"
    rig.write_text(
        '[cameras.front]\ntype = "zmq"\nserver_address = "127.0.0.1"\n'
        f"port = {server.port}\nwidth = 32\nheight = 24\nfovy_deg = 50.0\n"
        f"T_world_camera = {[*T, [0, 0, 0, 1]]}\n"
    )
    placed = PlacedCamera("front", (*map(tuple, T), (0, 0, 0, 1)), fovy_deg=50.0)
    robot = BeavrSimRobot(
        _robot_config(
            {"front": _zmq_robot_camera(server.port)},
            twin=("front",),
            camera_poses=str(rig),
            camera_max_age_s=1.0,  # a busy machine's scheduling never reads as a dead camera
            calibration_dir=tmp_path,
            image_height=24,
            image_width=32,
        )
    )
    assert robot.observation_features["front"] == robot.observation_features["front_twin"]
    robot.connect()
    try:
        obs = robot.get_observation()
        env = robot.twin.env
        data = env.render_data()
        cam = mujoco.mj_name2id(env.render_model, mujoco.mjtObj.mjOBJ_CAMERA, "front")
        np.testing.assert_allclose(data.cam_xpos[cam], placed.position, atol=1e-9)
        np.testing.assert_allclose(
            data.cam_xmat[cam].reshape(3, 3), placed.R_world_mujoco, atol=1e-6
        )
        assert env.render_model.cam_fovy[cam] == pytest.approx(50.0)
        real, twin = obs["front"], obs["front_twin"]
        assert real.shape == twin.shape == (24, 32, 3)
        assert np.ptp(real.astype(int)) < 40 < np.ptp(twin.astype(int))  # grey frame vs render
    finally:
        robot.disconnect()
    with pytest.raises(FileNotFoundError, match=r"camera_poses .*no such file"):
        _robot_config({}, camera_poses=str(tmp_path / "missing.toml"))


def test_lerobot_record_stores_the_robots_real_camera(server, tmp_path, monkeypatch):
    """``lerobot-record`` (its ``main``, in this process, from its command line: the plugins
    found as the installed command finds them) with ``--robot.cameras`` as for LeRobot's own
    robots: ``observation.images.wrist`` holds the camera's live frames."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.scripts.lerobot_record import main

    camera = (
        f"{{wrist: {{type: zmq, server_address: 127.0.0.1, port: {server.port}, "
        "camera_name: front, width: 32, height: 24, fps: 30, timeout_ms: 200}}"
    )
    argv = [
        "lerobot-record",
        "--robot.type=beavr_sim",
        "--robot.task=PickupBox",
        "--robot.camera_names=[]",
        f"--robot.cameras={camera}",
        f"--robot.calibration_dir={tmp_path / 'calibration'}",
        "--teleop.type=beavr_quest",
        "--teleop.source=trace",
        "--teleop.task=PickupBox",
        f"--teleop.calibration_dir={tmp_path / 'calibration'}",
        "--dataset.repo_id=local/robot_cams",
        f"--dataset.root={tmp_path / 'ds'}",
        "--dataset.num_episodes=1",
        "--dataset.episode_time_s=1",
        "--dataset.fps=30",
        "--dataset.single_task=watch",
        "--dataset.push_to_hub=false",
        "--dataset.video=false",
        "--play_sounds=false",
    ]
    monkeypatch.setattr(sys, "argv", argv)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        main()
    finally:  # LeRobot's init_logging replaced the root logger's handlers: later tests get theirs
        root.handlers[:] = handlers
        root.setLevel(level)
    ds = LeRobotDataset("local/robot_cams", root=tmp_path / "ds")
    assert ds.num_episodes == 1 and ds.num_frames >= 3
    assert ds.features["observation.images.wrist"]["shape"] == (24, 32, 3)
    levels = {round(float(ds[i]["observation.images.wrist"].mean()), 3) for i in range(len(ds))}
    assert len(levels) > len(ds) / 2  # the server's frames move on: not a frozen image


# --- depth (a RealSense's use_depth; no RealSense here: a stand-in of LeRobot's camera) --------


class _StandInRealSense:
    """What RealCameras reads of LeRobot's ``RealSenseCamera`` (its attribute names: a colour
    and a depth buffer of one capture, written under ``frame_lock`` by a read thread): capture
    ``i`` is colour ``i % 250`` and depth ``1000 + i`` mm."""

    def __init__(self, config) -> None:
        self.width, self.height, self.use_depth = config.width, config.height, config.use_depth
        self.frame_lock = threading.Lock()
        self.latest_color_frame = self.latest_depth_frame = self.latest_timestamp = None
        self.thread: threading.Thread | None = None
        self.stop = threading.Event()

    @property
    def is_connected(self) -> bool:
        return self.thread is not None

    def connect(self, warmup: bool = True) -> None:
        self.thread = threading.Thread(target=self._read_loop, daemon=True)
        self.thread.start()

    def _read_loop(self) -> None:
        i = 0
        while not self.stop.is_set():
            color = np.full((self.height, self.width, 3), i % 250, np.uint8)
            depth = np.full((self.height, self.width, 1), 1000 + i, np.uint16)
            with self.frame_lock:
                self.latest_color_frame, self.latest_depth_frame = color, depth
                self.latest_timestamp = time.perf_counter()
            i += 1
            self.stop.wait(0.01)

    def disconnect(self) -> None:
        self.stop.set()
        self.thread.join()


def _stand_in(configs):
    return {name: _StandInRealSense(config) for name, config in configs.items()}


def _realsense(depth: bool = True, **kw):
    from lerobot.cameras.realsense.configuration_realsense import RealSenseCameraConfig

    return RealSenseCameraConfig("123456789", fps=30, width=64, height=48, use_depth=depth, **kw)


@pytest.mark.parametrize("name, twin", [("wrist", "front"), ("front", "front_twin")])
def test_a_depth_camera_records_its_depth_as_its_own_feature_next_to_the_twins(name, twin):
    """A RealSense with ``use_depth`` (rig ``use_depth = true``) records
    ``observation.images.NAME_depth``: (H, W, 1) uint16 mm of the colour frame's capture,
    flagged ``is_depth_map`` (LeRobot's convention), next to the twin's ``front`` and
    ``front_depth``; a real ``front`` keeps its name and the twin's are ``front_twin``,
    ``front_twin_depth`` (``beavr_sim.cameras.names``)."""
    import gymnasium as gym
    from lerobot.datasets.feature_utils import validate_frame

    import beavr_sim  # noqa: F401  (registers the envs)
    from beavr_sim.datasets.features import RecordingConfig, lerobot_features
    from beavr_sim.datasets.recorder import EpisodeRecorder
    from beavr_sim.wire.records import Tick

    table = {"type": "intelrealsense", "serial_number_or_name": "123456789", "use_depth": True}
    assert parse_camera_table("wrist", {**table, "width": 64, "height": 48}).use_depth
    real = RealCameras({name: _realsense()}, control_period_s=1 / 30, make_cameras=_stand_in)
    real.connect()
    env = gym.make("beavr_sim/Playground-v0").unwrapped
    try:
        assert real.names == (name, name + "_depth")
        shapes = {n: real.frame_shape(n) for n in real.names}  # as the sessions declare them
        assert shapes == {name: (48, 64, 3), name + "_depth": (48, 64, 1)}
        config = RecordingConfig(
            cameras=("front",), depth_cameras=("front",), image_height=48, image_width=64,
            hand_keypoints=False,
        )  # fmt: skip
        features = lerobot_features(env.embodiment, config, real_cameras=shapes)
        assert features[f"observation.images.{name}_depth"]["info"] == {"is_depth_map": True}
        assert "info" not in features[f"observation.images.{name}"]
        assert f"observation.images.{twin}_depth" in features
        env.reset(seed=0)
        sink = FrameSink()
        recorder = EpisodeRecorder(sink, env, config, real_cameras=real)  # type: ignore[arg-type]
        recorder.begin()

        class _State:
            action = env.joints.home.copy()

        for _ in range(2):
            recorder(Tick(t=0.0, frames=(), commands={}, state=_State()))  # type: ignore[arg-type]
        recorder.close()
    finally:
        real.close()
        env.close()
    for frame in sink.frames:
        validate_frame(frame, features)  # LeRobot's own check of each feature's dtype, shape
        color, depth = (
            frame[f"observation.images.{name}"],
            frame[f"observation.images.{name}_depth"],
        )
        assert depth.dtype == np.uint16 and depth.shape == (48, 64, 1)
        assert (int(depth[0, 0, 0]) - 1000) % 250 == int(color[0, 0, 0])  # one capture
        assert frame[f"observation.images.{twin}_depth"].dtype == np.float32  # the twin's
        assert np.ptp(frame[f"observation.images.{twin}"].astype(int)) > 40  # a render
    assert real.summary()[name]["frames"] == 3  # at begin, then after each frame


def test_depth_camera_config_errors_are_one_line():
    with pytest.raises(CameraSpecError, match=r"'wrist': use_rgb = false is not supported"):
        RealCameras({"wrist": _realsense(use_rgb=False)}, control_period_s=1 / 30)
    with pytest.raises(CameraSpecError, match=r"'wrist_depth' is also camera 'wrist'"):
        RealCameras(
            {"wrist": _realsense(), "wrist_depth": _realsense(depth=False)}, control_period_s=0.1
        )


def test_the_robot_declares_a_depth_cameras_depth_as_its_own_feature():
    """``--robot.cameras`` with a RealSense's ``use_depth``: the robot's observation features
    name ``NAME_depth`` (H, W, 1) beside the colour image, as LeRobot's robots do, so
    ``lerobot-record`` keeps the depth its observation carries."""
    from beavr_sim.integrations.robot import BeavrSimRobot

    robot = BeavrSimRobot(_robot_config({"wrist": _realsense()}, twin=("front",)))
    features = robot.observation_features
    assert features["wrist"] == (48, 64, 3) and features["wrist_depth"] == (48, 64, 1)
    assert "front_depth" not in features  # a twin camera's depth is asked for by name
    plain = BeavrSimRobot(_robot_config({"wrist": _realsense(depth=False)}))
    assert "wrist_depth" not in plain.observation_features
