"""Twin cameras placed from a rig file's [cameras.NAME] poses, and twin depth recorded as
LeRobot's ``<camera>_depth`` feature."""

from __future__ import annotations

import math
import time

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from fixtures_shared import FrameSink
from lerobot.datasets.feature_utils import validate_frame

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.cameras.errors import CameraSpecError
from beavr_sim.cameras.poses import placed_camera, rig_placed_cameras
from beavr_sim.cameras.spec import parse_camera_table, rig_cameras
from beavr_sim.datasets.cli import parse_cameras
from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.datasets.recorder import EpisodeRecorder
from beavr_sim.envs.cameras import render_option
from beavr_sim.naming import UnknownNameError
from beavr_sim.wire.records import Tick

# The front camera moved to a calibrated pose (optical frame: looking along world -x, tilted
# 30 degrees down, image x towards world +y) and a new side camera with a field of view.
_C, _S = math.cos(math.radians(30)), math.sin(math.radians(30))
R_FRONT = np.column_stack([[0.0, 1.0, 0.0], [_S, 0.0, -_C], [-_C, 0.0, -_S]])
P_FRONT = [1.3, 0.05, 1.2]
RIG = f"""
[[devices]]
name = "right_arm"
kind = "xarm7"
effector = "right"
host = "127.0.0.1"

[cameras.front]
type = "opencv"
index_or_path = 0
width = 640
height = 480
fx = 600.0
fy = 600.0
cx = 322.0
cy = 236.0
T_world_camera = [
    [{R_FRONT[0, 0]}, {R_FRONT[0, 1]}, {R_FRONT[0, 2]}, {P_FRONT[0]}],
    [{R_FRONT[1, 0]}, {R_FRONT[1, 1]}, {R_FRONT[1, 2]}, {P_FRONT[1]}],
    [{R_FRONT[2, 0]}, {R_FRONT[2, 1]}, {R_FRONT[2, 2]}, {P_FRONT[2]}],
    [0, 0, 0, 1],
]

[cameras.side]
type = "zmq"
server_address = "127.0.0.1"
port = 5555
fovy_deg = 50.0
T_world_camera = [[1, 0, 0, 0.4], [0, 0, 1, -0.9], [0, -1, 0, 1.1], [0, 0, 0, 1]]
"""


def test_rig_pose_places_the_twin_camera(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    assert set(rig_cameras(rig)) == {"front", "side"}  # LeRobot configs without the pose keys
    placed = {c.name: c for c in rig_placed_cameras(rig)}
    assert placed["front"].intrinsics.cx == 322.0 and placed["side"].fovy_deg == 50.0
    env = gym.make(
        "beavr_sim/Playground-v0", placed_cameras=tuple(placed.values()), cameras=("front", "side")
    ).unwrapped
    env.reset(seed=0)
    for model, data in ((env.model, env.data), (env.render_model, env.render_data())):
        for name, R_optical, p in (("front", R_FRONT, P_FRONT), ("side", None, (0.4, -0.9, 1.1))):
            cam = model.camera(name).id
            np.testing.assert_allclose(data.cam_xpos[cam], p, atol=1e-9)
            if R_optical is not None:
                # MuJoCo's camera frame: the optical frame's x, and -y, -z (looks along -z).
                R_mujoco = data.cam_xmat[cam].reshape(3, 3)
                np.testing.assert_allclose(R_mujoco, R_optical @ np.diag([1, -1, -1]), atol=1e-9)
    side = env.render_model.camera("side").id
    assert env.render_model.cam_fovy[side] == pytest.approx(50.0)
    # The side camera (optical z along world +y) looks at the table from -y: world +y is
    # along its axis, i.e. MuJoCo's -z.
    np.testing.assert_allclose(env.data.cam_xmat[side].reshape(3, 3)[:, 2], [0, -1, 0], atol=1e-9)
    env.close()


@pytest.mark.parametrize(
    "extra, message",
    [
        ({"fx": 600.0}, "intrinsics need all of fx, fy, cx, cy, width, height"),
        ({}, "needs the field of view"),
        ({"fovy_deg": 50, "T_world_camera": [[1, 0, 0, 0]] * 4}, "last row must be"),
        (
            {
                "fovy_deg": 50,
                "T_world_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
            },
            "not a rotation",
        ),
    ],
)
def test_rig_pose_errors_name_the_camera(extra, message):
    table = {"type": "opencv", "index_or_path": 0}
    table.setdefault("T_world_camera", np.eye(4).tolist())
    table.update(extra)

    with pytest.raises(CameraSpecError, match=message) as err:
        placed_camera("wrist", table)
    assert "'wrist'" in str(err.value) and "\n" not in str(err.value)


def test_unknown_rig_key_lists_the_pose_keys():
    with pytest.raises(CameraSpecError, match="T_world_camera") as err:
        parse_camera_table("wrist", {"type": "opencv", "index_or_path": 0, "pose": [0, 0, 0]})
    assert "fovy_deg" in str(err.value)


def test_cameras_option_takes_depth():
    assert parse_cameras("front,front:depth,overhead") == (("front", "overhead"), ("front",))
    assert parse_cameras("overhead:depth") == ((), ("overhead",))
    with pytest.raises(ValueError, match="NAME or NAME:depth"):
        parse_cameras("front:ir")
    with pytest.raises(ValueError, match="Valid depth cameras"):
        RecordingConfig(depth_cameras=("frnt",))


def _ray_depths(model, data, camera: str, height: int, width: int, step: int = 6) -> tuple:
    """Depth along the camera's axis at every ``step``-th pixel centre, by casting rays
    through the visible geom groups (independent of the renderer's depth buffer)."""
    cam = model.camera(camera).id
    R = data.cam_xmat[cam].reshape(3, 3)
    focal = (height / 2) / math.tan(math.radians(model.cam_fovy[cam]) / 2)
    groups = np.array(render_option().geomgroup, dtype=np.uint8)
    hit = np.array([-1], dtype=np.int32)
    pixels, depths = [], []
    for v in range(step // 2, height, step):
        for u in range(step // 2, width, step):
            d_cam = np.array([(u + 0.5 - width / 2) / focal, -(v + 0.5 - height / 2) / focal, -1.0])
            d_world = R @ (d_cam / np.linalg.norm(d_cam))
            r = mujoco.mj_ray(model, data, data.cam_xpos[cam], d_world, groups, 1, -1, hit)
            if r > 0:
                pixels.append((v, u))
                depths.append(r / np.linalg.norm(d_cam))  # along the axis (d_cam's z is -1)
    return pixels, np.array(depths)


def test_twin_depth_recorded_in_metres():
    env = gym.make("beavr_sim/Playground-v0").unwrapped
    env.reset(seed=0)
    config = RecordingConfig(
        cameras=("front",),
        depth_cameras=("front",),
        image_height=48,
        image_width=64,
        hand_keypoints=False,
    )
    features = lerobot_features(env.embodiment, config, env.environment_state_names)
    depth_key = "observation.images.front_depth"
    assert features[depth_key]["shape"] == (48, 64, 1)
    assert features[depth_key]["info"] == {"is_depth_map": True}
    sink = FrameSink()
    recorder = EpisodeRecorder(sink, env, config)  # type: ignore[arg-type]
    recorder.begin()

    class _State:
        action = env.joints.home.copy()

    recorder(Tick(t=0.0, frames=(), commands={}, state=_State()))  # type: ignore[arg-type]
    recorder.close()
    (frame,) = sink.frames
    validate_frame(frame, features)  # LeRobot's own check of every feature's dtype and shape
    depth = frame[depth_key]
    assert depth.dtype == np.float32 and depth.shape == (48, 64, 1)
    pixels, expected = _ray_depths(env.render_model, env.render_data(), "front", 48, 64)
    env.close()
    assert len(pixels) > 50 and 0.5 < np.median(expected) < 3.0  # the table and the robot
    got = np.array([depth[v, u, 0] for v, u in pixels])
    # Pixels on an edge may see the other side of it; the bulk agrees to a few millimetres.
    assert np.median(np.abs(got - expected)) < 0.005
    assert np.mean(np.abs(got - expected) < 0.02) > 0.9


def test_session_camera_poses_place_the_twin_camera(tmp_path, monkeypatch):
    from beavr_sim.assets import bundled_trace
    from beavr_sim.teleop import session
    from beavr_sim.teleop.processes import process_configs
    from beavr_sim.teleop.twin_process import make_twin_env

    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    common = dict(task="PickupBox", source="trace", trace=bundled_trace("PickupBox"))
    options = session.SessionOptions(
        **common, viser=False, headless=True, progress=False, camera_poses=rig
    )
    assert [c.name for c in options.placed_cameras] == ["front", "side"]

    class _Built(Exception):
        pass

    made = {}

    def make(env_id, **kwargs):  # the session's twin env: its arguments, then stop
        made.update(kwargs)
        raise _Built

    monkeypatch.setattr(session.gym, "make", make)
    with pytest.raises(_Built):
        session.build_loop(options)
    assert made["placed_cameras"] == options.placed_cameras  # (placement: the test above)
    # --multiprocess (main refused it): the twin process's env gets the same cameras
    multi = session.SessionOptions(
        **common, viser=False, multiprocess=True, headless=True, camera_poses=rig
    )
    _, twin = process_configs(multi)
    assert twin.placed_cameras == options.placed_cameras
    made.clear()
    with pytest.raises(_Built):
        make_twin_env(twin)
    assert made["placed_cameras"] == options.placed_cameras
    bare = tmp_path / "bare.toml"
    bare.write_text('[cameras.front]\ntype = "opencv"\nindex_or_path = 0\n')
    with pytest.raises(ValueError, match=r"no \[cameras\.NAME\] table has a T_world_camera"):
        session.SessionOptions(**common, viser=False, headless=True, camera_poses=bare)


def test_a_placed_camera_of_a_new_name_is_recorded_as_its_render(tmp_path):
    from beavr_sim.assets import bundled_trace
    from beavr_sim.teleop.__main__ import build_parser
    from beavr_sim.teleop.session import SessionOptions

    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    common = ["--task", "PickupBox", "--source", "trace", "--no-viser", "--headless"]
    common += ["--record", str(tmp_path / "d"), "--image-size", "48x64"]
    args = build_parser().parse_args([*common, "--cameras", "side,side:depth"])
    with pytest.raises(UnknownNameError, match=r"Unknown camera 'side'\. Valid cameras: front"):
        SessionOptions.from_args(args)  # not placed: refused, naming the valid ones
    args = build_parser().parse_args(
        [*common, "--cameras", "side,side:depth", "--camera-poses", str(rig)]
    )
    options = SessionOptions.from_args(args)
    config = options.recording
    assert config.cameras == ("side",) and config.depth_cameras == ("side",)
    with pytest.raises(ValueError, match="where --camera-poses places it"):
        SessionOptions(
            task="PickupBox", source="trace", trace=bundled_trace("PickupBox"), viser=False,
            headless=True, record=tmp_path / "e", recording=config,
        )  # fmt: skip

    # The recorder draws the placed camera: the frame is the render from its pose.
    env = gym.make("beavr_sim/Playground-v0", placed_cameras=options.placed_cameras).unwrapped
    env.reset(seed=0)
    features = lerobot_features(env.embodiment, config, env.environment_state_names)
    sink = FrameSink()
    recorder = EpisodeRecorder(sink, env, config)  # type: ignore[arg-type]
    recorder.begin()

    class _State:
        action = env.joints.home.copy()

    recorder(Tick(t=0.0, frames=(), commands={}, state=_State()))  # type: ignore[arg-type]
    recorder.close()
    (frame,) = sink.frames
    validate_frame(frame, features)
    direct = mujoco.Renderer(env.render_model, 48, 64)

    def render(camera: str) -> np.ndarray:
        direct.update_scene(env.render_data(), camera=camera, scene_option=render_option())
        direct.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        direct.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        return direct.render().copy()

    expected, front = render("side"), render("front")
    side = env.render_model.camera("side").id
    placed_at = env.render_data().cam_xpos[side].copy()
    direct.close()
    env.close()
    image = frame["observation.images.side"]
    assert image.shape == (48, 64, 3)
    np.testing.assert_array_equal(image, expected)
    assert not np.array_equal(image, front)  # not some other camera's view
    np.testing.assert_allclose(placed_at, [0.4, -0.9, 1.1], atol=1e-9)
    depth = frame["observation.images.side_depth"]
    assert depth.shape == (48, 64, 1) and np.isfinite(depth).all()


def test_twin_camera_feed_copies_the_pose_on_the_tick_and_renders_it_later(tmp_path):
    from beavr_sim.teleop.twin_camera_feed import TwinCameraFeed

    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    env = gym.make("beavr_sim/Playground-v0", placed_cameras=rig_placed_cameras(rig)).unwrapped
    env.reset(seed=0)
    now = [100.0]
    feed = TwinCameraFeed(env.render_model, env.data, "front", rate_hz=10.0, clock=lambda: now[0])
    shapes = {"side": (48, 64, 3), "wrist": (48, 64, 3), "big": (960, 1280, 3)}
    shapes["side_depth"] = (48, 64, 1)  # one channel: camera side's depth (a depth panel)
    assert feed.render(shapes) == ({}, None)  # no tick yet: nothing to draw
    assert feed.camera_for("side") == "side" and feed.camera_for("wrist") == "front"
    assert feed.panel_shape("front") == (480, 640, 3)  # its intrinsics' size
    assert feed.panel_shape("side") == (480, 640, 3)  # a field of view only: the default size

    tick = Tick(t=0.0, frames=(), commands={}, state=None)  # type: ignore[arg-type]
    feed(tick)
    now[0] += 0.05
    feed(tick)  # within the period: no copy
    assert feed.copies == 1
    direct = mujoco.Renderer(env.render_model, 48, 64)

    def render(camera: str) -> np.ndarray:
        direct.update_scene(env.render_data(), camera=camera, scene_option=render_option())
        direct.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        direct.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        return direct.render().copy()

    expected = {"side": render("side"), "wrist": render("front")}
    direct.enable_depth_rendering()
    expected["side_depth"] = render("side")[..., None]
    direct.disable_depth_rendering()
    env.data.qpos[env.joints.qpos_adr[0]] += 0.5  # the twin moves on; no tick copies it
    images, age_s = feed.render(shapes)
    moved = render("front")
    direct.close()
    feed.close()
    env.close()
    np.testing.assert_array_equal(images["side"], expected["side"])
    np.testing.assert_array_equal(images["wrist"], expected["wrist"])  # the pose copied
    assert images["side_depth"].dtype == np.float32 and images["side_depth"].shape == (48, 64, 1)
    np.testing.assert_allclose(images["side_depth"], expected["side_depth"], rtol=1e-6)
    assert not np.array_equal(moved, expected["wrist"])  # (the move shows in a live render)
    assert images["big"].shape == (480, 640, 3)  # scaled into the offscreen buffer
    assert age_s == pytest.approx(0.05)


def test_datasets_generate_places_the_twin_cameras_of_camera_poses(tmp_path, monkeypatch):
    """``datasets generate --camera-poses F`` (teleop's option and loader): the twin camera F
    places, ``Side`` (its name kept as given, in the table and in ``--cameras``), is recorded
    with its depth. Cheap: the bundled trace stands in for the synthesized one, 0.2 s kept."""
    import json

    import pyarrow.parquet as pq

    import beavr_sim.synthetic.trace as synthetic_trace
    from beavr_sim.assets import bundled_trace
    from beavr_sim.datasets.__main__ import main

    class _Synth:
        class summary:
            success = True

    monkeypatch.setattr(synthetic_trace, "synthesize", lambda *a, **k: _Synth())
    monkeypatch.setattr(synthetic_trace, "write_trace", lambda *a: bundled_trace("PickupBox"))
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG.replace("[cameras.side]", "[cameras.Side]"))
    out = tmp_path / "d"
    common = ["generate", "--task", "PickupBox", "--episodes", "1", "--out", str(out)]
    common += ["--image-size", "24x32", "--episode-seconds", "0.2", "--keep-failed"]
    common += ["--workers", "1", "--quiet", "--no-videos", "--no-keypoints"]
    assert main([*common, "--cameras", "Side"]) == 2  # not placed: refused (one line)
    assert main([*common, "--cameras", "Side,Side:depth", "--camera-poses", str(rig)]) == 0
    features = json.loads((out / "meta" / "info.json").read_text())["features"]
    assert features["observation.images.Side"]["shape"] == [24, 32, 3]
    assert features["observation.images.Side_depth"]["info"]["is_depth_map"] is True
    table = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet")
    assert table.num_rows >= 6  # 0.2 s at 30 fps, each drawn from the placed camera
    assert {"observation.images.Side", "observation.images.Side_depth"} <= set(table.column_names)
    bare = tmp_path / "bare.toml"
    bare.write_text('[cameras.front]\ntype = "opencv"\nindex_or_path = 0\n')
    assert main([*common, "--camera-poses", str(bare), "--overwrite"]) == 2


def test_a_twin_only_session_streams_the_twin_depth_it_records(tmp_path):
    """No real camera, --cameras front,front:depth: the streamed panels are the twin's front
    and its depth panel front_depth (the twin's depth, in the real depth panels' colours,
    labelled as the twin's), through the one stream both layouts start."""
    import threading

    from waiting import HANG_GUARD_S

    from beavr_sim.assets import bundled_trace
    from beavr_sim.cameras.stream import LIVE, StreamConfig, colour_depth
    from beavr_sim.teleop.camera_viewers import CameraViewers, start_camera_stream
    from beavr_sim.teleop.processes import process_configs
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.teleop.twin_camera_feed import twin_feed

    common = dict(task="PickupBox", source="trace", trace=bundled_trace("PickupBox"))
    common.update(viser=False, headless=True, progress=False, camera_stream_hz=5.0)
    recording = RecordingConfig(cameras=("front",), depth_cameras=("front",))
    options = SessionOptions(**common, record=tmp_path / "d", recording=recording)
    assert options.streamed_twin_depth == ("front",)
    multi = SessionOptions(**common, record=tmp_path / "e", recording=recording, multiprocess=True)
    _, twin = process_configs(multi)  # --multiprocess: the twin process's stream gets it too
    assert twin.camera_stream.depth == ("front",)
    assert SessionOptions(**common).streamed_twin_depth == ()  # recording nothing: colour only

    env = gym.make("beavr_sim/Playground-v0").unwrapped
    env.reset(seed=0)
    feed, panels = twin_feed(env, 50.0)
    feed(Tick(t=0.0, frames=(), commands={}, state=None))  # type: ignore[arg-type]
    arrived, seen, shapes = threading.Event(), {}, {}

    class _Panel:
        def __call__(self, frame):
            seen[frame.name] = frame
            if frame.name == "front_depth" and frame.state == LIVE:
                arrived.set()

        def attach(self, stream):
            pass

    class _View:
        def add_camera_panel(self, panel_shapes):
            shapes.update(panel_shapes)
            return _Panel()

    viewers = CameraViewers(view=_View(), twin=feed, twin_panels=panels, twin_depth=("front",))
    stream = start_camera_stream(None, StreamConfig(rate_hz=50.0), viewers)
    try:
        # The twin keeps ticking while the stream starts (its first render may come later than
        # a single pose copy stays live on a busy machine: that panel is rightly NO SIGNAL).
        deadline = time.monotonic() + HANG_GUARD_S
        while not arrived.wait(0.05):
            assert time.monotonic() < deadline, "no live twin depth panel"
            feed(Tick(t=0.0, frames=(), commands={}, state=None))  # type: ignore[arg-type]
    finally:
        stream.close()
    height, width = feed.panel_shape("front")[:2]
    direct = mujoco.Renderer(env.render_model, height, width)
    direct.enable_depth_rendering()
    direct.update_scene(env.render_data(), camera="front", scene_option=render_option())
    expected = colour_depth(direct.render()[..., None])
    direct.close()
    env.close()
    assert panels == ("front",)
    assert shapes == {"front": (height, width, 3), "front_depth": (height, width, 1)}
    depth = seen["front_depth"]
    assert depth.label.startswith("front_depth: live, age ")
    assert depth.label.endswith("(depth 0.2-2 m, twin)")  # the twin's depth, its colours
    assert depth.image.shape == (height, width, 3)
    assert np.abs(depth.image.astype(int) - expected).mean() < 1.0  # the twin's depth, coloured
    assert not np.array_equal(depth.image, seen["front"].image)  # not the colour render
