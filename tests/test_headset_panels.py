"""What the headset and the browser are streamed (``--camera-stream-hz``): a depth camera's depth
as a coloured panel (fixed range, invalid black; the twin's depth as its twin half), every
camera in the Quest app's one panel image (a labelled grid), and the WebXR page's in-scene panel
moved by the page (its offset, kept in localStorage; the page's module run by node)."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from beavr_sim.cameras.headset_panels import QuestCameraSink, grid_layout, quest_grid
from beavr_sim.cameras.real import Grab, RealCameras
from beavr_sim.cameras.stream import (
    DEPTH_RANGE_M,
    LIVE,
    NO_SIGNAL,
    CameraStream,
    StreamConfig,
    StreamFrame,
    colour_depth,
)
from beavr_sim.headset.quest_io import encode_jpeg
from beavr_sim.headset.webxr_server import STATIC_DIR

WAIT_S = 20.0  # readiness deadline, never a pass/fail timing bound
H, W = 48, 64
NEAR = colour_depth(np.array([[DEPTH_RANGE_M[0]]], np.float32))[0, 0].astype(int)
FAR = colour_depth(np.array([[DEPTH_RANGE_M[1]]], np.float32))[0, 0].astype(int)


def _depth_mm() -> np.ndarray:
    """Left third 100 mm (nearer than the range), middle 3 m (farther), right third 0 (none)."""
    depth = np.zeros((H, W, 1), np.uint16)
    depth[:, : W // 3] = 100
    depth[:, W // 3 : 2 * W // 3] = 3000
    return depth


def _close(pixels: np.ndarray, colour: np.ndarray, tol: int = 3) -> bool:
    return bool(np.abs(pixels.reshape(-1, 3).astype(int) - colour).max() <= tol)


# --- depth ------------------------------------------------------------------------------------


def test_depth_colours_are_fixed_near_blue_far_red_and_no_depth_black():
    assert NEAR[2] > NEAR[0] and FAR[0] > FAR[2]  # blue near, red far
    assert NEAR.sum() > 60 and FAR.sum() > 60  # no valid depth reads black
    image = colour_depth(_depth_mm())
    assert image.shape == (H, W, 3) and image.dtype == np.uint8
    assert _close(image[:, : W // 3], NEAR)  # clamped to the near colour
    assert _close(image[:, W // 3 : 2 * W // 3], FAR)  # clamped to the far colour
    assert (image[:, 2 * W // 3 :] == 0).all()  # 0 mm: no reading, black
    metres = np.array([[np.nan, 0.0, 0.2, 2.0, 1.1]], np.float32)  # the twin's, in metres
    row = colour_depth(metres)[0].astype(int)
    assert (row[:2] == 0).all() and _close(row[2], NEAR) and _close(row[3], FAR)
    assert row[4][1] > max(row[4][0], row[4][2])  # mid-range: green


class _Twin:
    """A TwinSource whose depth (asked by a one-channel shape) is 3 m and colour is grey 60."""

    def __init__(self) -> None:
        self.asked: list[dict] = []

    def render(self, shapes):
        self.asked.append(dict(shapes))
        out = {}
        for name, shape in shapes.items():
            if shape[2] == 1:
                out[name] = np.full((shape[0], shape[1], 1), 3.0, np.float32)
            else:
                out[name] = np.full((shape[0], shape[1], 3), 60, np.uint8)
        return out, 0.02

    def camera_for(self, panel: str) -> str:
        return panel

    def close(self) -> None:
        pass


def _depth_grab(dead: tuple[str, ...] = ()) -> Grab:
    if dead:
        return Grab(frames={}, ages_s={}, dead=dead)
    frames = {"wrist": np.full((H, W, 3), 200, np.uint8), "wrist_depth": _depth_mm()}
    return Grab(frames=frames, ages_s={"wrist": 0.01}, dead=())


def test_a_depth_panel_is_coloured_and_composed_in_the_view_chosen():
    shapes = {"wrist": (H, W, 3), "wrist_depth": (H, W, 1)}
    twin = _Twin()
    stream = CameraStream(
        StreamConfig(rate_hz=0, view="real"), [], shapes, twin=twin,
        depth={"wrist_depth": "wrist"},
    )  # fmt: skip
    now = time.perf_counter
    colour, depth = stream.panels(_depth_grab(), None, now())
    assert colour.state == LIVE and colour.image.mean() == 200
    assert depth.state == LIVE and depth.image.shape == (H, W, 3)
    assert depth.age_s == pytest.approx(colour.age_s)  # the same capture's age
    assert _close(depth.image[:, : W // 3], NEAR) and (depth.image[:, 2 * W // 3 :] == 0).all()
    assert "depth 0.2-2 m" in depth.label
    stream.set_view("both")  # the real depth beside the twin's depth of the same camera
    colour, depth = stream.panels(_depth_grab(), None, now())
    assert twin.asked[-1] == {"wrist": (H, W, 3), "wrist_depth": (H, W, 1)}
    assert depth.image.shape == (H, 2 * W, 3)
    assert _close(depth.image[:, : W // 3], NEAR) and _close(depth.image[:, W:], FAR)
    assert colour.image[:, W:].mean() == 60  # the colour panel's twin half: its colour
    colour, depth = stream.panels(_depth_grab(dead=("wrist",)), None, now())
    assert depth.state == NO_SIGNAL and colour.state == NO_SIGNAL  # the camera's signal is theirs


class _StandInDepthCamera:
    """What RealCameras reads of LeRobot's RealSenseCamera: a colour and a depth buffer of one
    capture under ``frame_lock``, from a read thread."""

    def __init__(self, config) -> None:
        self.width, self.height = config.width, config.height
        self.frame_lock = threading.Lock()
        self.latest_color_frame = np.full((H, W, 3), 200, np.uint8)
        self.latest_depth_frame = _depth_mm()
        self.latest_timestamp = time.perf_counter()
        self.stop = threading.Event()
        self.thread: threading.Thread | None = None
        self.is_connected = False

    def connect(self, warmup: bool = True) -> None:
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        self.is_connected = True

    def _run(self) -> None:
        while not self.stop.wait(0.01):
            with self.frame_lock:
                self.latest_timestamp = time.perf_counter()

    def disconnect(self) -> None:
        self.stop.set()
        self.thread.join()


class _QuestPublisher:
    """A ``HeadsetImagePublisher`` stand-in: the JPEG bytes it would send."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []
        self.arrived = threading.Event()

    def publish(self, image) -> bool:
        self.sent.append(encode_jpeg(image, 90))
        self.arrived.set()
        return True

    def wait(self) -> np.ndarray:
        assert self.arrived.wait(WAIT_S), "no image reached the Quest publisher"
        return np.asarray(Image.open(io.BytesIO(self.sent[-1])))


def _depth_cameras() -> RealCameras:
    """A connected ``RealCameras`` of one stand-in depth camera ``wrist``."""
    from lerobot.cameras.realsense.configuration_realsense import RealSenseCameraConfig

    config = RealSenseCameraConfig("1", fps=30, width=W, height=H, use_depth=True)
    real = RealCameras(
        {"wrist": config}, control_period_s=1 / 30,
        make_cameras=lambda configs: {n: _StandInDepthCamera(c) for n, c in configs.items()},
    )  # fmt: skip
    real.connect()
    return real


def _first_quest_image(config: StreamConfig):
    """The first image the Quest publisher gets from a stream of :func:`_depth_cameras` under
    ``config``, and the stream (closed)."""
    from beavr_sim.teleop.camera_viewers import CameraViewers, start_camera_stream

    real = _depth_cameras()
    quest = _QuestPublisher()
    try:
        assert "wrist_depth" in real.peek().frames
        stream = start_camera_stream(real, config, CameraViewers(quest=quest))
        try:
            return quest.wait(), stream
        finally:
            stream.close()
    finally:
        real.close()


def test_a_depth_cameras_depth_reaches_the_quest_panel_beside_its_colour():
    """``RealCameras.peek`` gives the depth map too; the Quest panel's one image is the colour
    panel and the coloured depth panel side by side."""
    image, _ = _first_quest_image(StreamConfig(rate_hz=50.0))
    assert image.shape == (H, 2 * W, 3)
    body = slice(H // 2, H)  # below the tiles' labels
    assert abs(float(image[body, 4 : W // 3 - 4].mean()) - 200) < 6  # wrist's colour
    depth = image[body, W:]
    assert _close(depth[:, 4 : W // 3 - 4], NEAR, 12)  # near: blue
    assert _close(depth[:, W // 3 + 4 : 2 * W // 3 - 4], FAR, 12)  # far: red
    assert depth[:, 2 * W // 3 + 4 :].max() < 25  # no depth: black


def test_the_quest_panel_shows_only_the_panels_chosen():
    """--quest-cameras wrist_depth: the Quest image is the depth panel alone (no grid, no
    colour tile), while the stream still composes every panel for the other viewers."""
    image, stream = _first_quest_image(StreamConfig(rate_hz=50.0, quest_panels=("wrist_depth",)))
    assert stream.shapes.keys() == {"wrist", "wrist_depth"}  # both still streamed
    assert image.shape == (H, W, 3)  # one panel: its image, not a grid of two
    assert _close(image[:, 4 : W // 3 - 4], NEAR, 12)  # the depth's colours, not wrist's grey
    assert _close(image[:, W // 3 + 4 : 2 * W // 3 - 4], FAR, 12)


def test_an_unknown_quest_camera_is_one_line_naming_the_panels():
    from beavr_sim.naming import UnknownNameError
    from beavr_sim.teleop.camera_viewers import CameraViewers, start_camera_stream

    real = _depth_cameras()
    quest = _QuestPublisher()
    try:
        config = StreamConfig(rate_hz=50.0, quest_panels=("wrist", "wirst_depth"))
        with pytest.raises(UnknownNameError) as caught:
            start_camera_stream(real, config, CameraViewers(quest=quest))
    finally:
        real.close()
    message = str(caught.value)
    assert "\n" not in message and "'wirst_depth' (--quest-cameras)" in message
    assert message.endswith("Valid Quest camera panels (--quest-cameras): wrist, wrist_depth.")
    assert quest.sent == []


def test_quest_cameras_is_one_option_of_both_layouts():
    """--quest-cameras reaches the one StreamConfig both layouts start their stream from; the
    --multiprocess twin checks the names against its panels at its start (a bad one: the
    supervisor's bad input), and the option needs a Quest and a stream."""
    from types import SimpleNamespace

    from beavr_sim.assets import bundled_trace
    from beavr_sim.naming import UnknownNameError
    from beavr_sim.teleop.__main__ import build_parser
    from beavr_sim.teleop.processes import process_configs
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.teleop.twin_camera_stream import TwinCameraStream, check_quest_panels
    from beavr_sim.teleop.twin_process import BAD_INPUT, _fail_start

    trace = ["--source", "trace", "--trace", str(bundled_trace("PickupBox"))]
    argv = ["--task", "PickupBox", "--no-viser", "--camera-stream-hz", "5"]
    argv += ["--quest-cameras", "front, front_depth"]
    with pytest.raises(ValueError, match=r"--quest-cameras .* needs --camera-stream-hz HZ and "):
        SessionOptions.from_args(build_parser().parse_args([*argv, *trace]))  # no Quest
    options = SessionOptions.from_args(build_parser().parse_args([*argv, "--multiprocess"]))
    assert options.camera_stream_config().quest_panels == ("front", "front_depth")
    _, twin = process_configs(options)
    assert twin.camera_stream.stream == options.camera_stream_config()

    env = SimpleNamespace(embodiment=SimpleNamespace(cameras=()))  # the headset camera: front
    stream = TwinCameraStream(options.camera_stream_config(), depth=("front",), quest=True)
    assert check_quest_panels(stream, env, None) == ("front", "front_depth")
    assert stream.quest_shows_panels(None)  # chosen: the Quest shows them, not headset images
    bare = TwinCameraStream(StreamConfig(5.0), quest=True)
    assert not bare.quest_shows_panels(None)  # not chosen, no real camera: headset images
    side = TwinCameraStream(StreamConfig(5.0, quest_panels=("side",)), quest=True)
    with pytest.raises(UnknownNameError, match=r"Valid Quest camera panels .*: front\.$") as bad:
        check_quest_panels(side, env, None)
    sent: list = []
    _fail_start(SimpleNamespace(send_bytes=sent.append), SimpleNamespace(close=list), [], bad.value)
    assert sent[0].decode().startswith(BAD_INPUT + "Unknown Quest camera panel 'side'")


# --- every camera on the Quest panel ----------------------------------------------------------


def _frame(name: str, level: int, shape=(H, W, 3), state: str = LIVE) -> StreamFrame:
    return StreamFrame(name, np.full(shape, level, np.uint8), state, 0.01, 1)


def test_two_cameras_are_both_on_the_quest_panel_each_labelled():
    quest = _QuestPublisher()
    sink = QuestCameraSink(quest, ("a", "b"))
    sink(_frame("a", 40))
    assert quest.sent == []  # a round ends with its last panel
    sink(_frame("b", 220))
    image = np.asarray(Image.open(io.BytesIO(quest.sent[-1])))
    assert image.shape == (H, 2 * W, 3)  # side by side, at their own size
    body = slice(H // 2, H)
    assert abs(float(image[body, :W].mean()) - 40) < 4  # left: camera a
    assert abs(float(image[body, W:].mean()) - 220) < 4  # right: camera b
    assert image[:8, :W].std() > 5 and image[:8, W:].std() > 5  # each tile's label line
    one = quest_grid([_frame("a", 40)])
    assert one.shape == (H, W, 3) and one.mean() == 40  # one camera: its panel alone


def test_the_quest_grid_fits_the_panel_and_a_panel_not_seen_is_no_signal():
    assert grid_layout(2, (480, 640)) == (1, 2, 1.0)
    assert grid_layout(4, (480, 640)) == (2, 2, 1.0)
    assert grid_layout(2, (480, 1280)) == (2, 1, 1.0)  # two `both` panels: one above the other
    rows, cols, scale = grid_layout(5, (480, 640))
    assert rows * cols >= 5 and rows * 480 * scale <= 960 and cols * 640 * scale <= 1280
    image = quest_grid([_frame("a", 40, (480, 640, 3)), "b", _frame("c", 90, (480, 640, 3))])
    assert image.shape[0] <= 960 and image.shape[1] <= 1280
    assert image.shape == (960, 1280, 3)  # 2x2 tiles of 480x640
    b = image[240:480, 640:]  # b's tile: never seen, NO SIGNAL (its grey, red writing)
    assert abs(float(np.median(b)) - 40) < 3 and (b[..., 0].astype(int) - b[..., 1] > 100).any()
    assert (image[480:, 640:] == 0).all()  # the empty fourth tile


# --- the WebXR page's panel offset (node) -----------------------------------------------------

NODE = shutil.which("node")
_NODE_SCRIPT = """
import { PanelOffset } from %(offset)s;
import { quadVertices } from %(quad)s;
class Store {
  constructor(items) { this.items = items; }
  getItem(k) { return k in this.items ? this.items[k] : null; }
  setItem(k, v) { this.items[k] = String(v); }
}
const items = {};
const a = new PanelOffset(new Store(items));
const fresh = a.value.slice();
a.step("right"); a.step("right"); a.step("up"); a.step("nearer");
const moved = a.value.slice();
const stored = items[a.key];
const reloaded = new PanelOffset(new Store(items)).value;
const far = new PanelOffset(new Store({}));
for (let i = 0; i < 100; i++) far.step("farther");
const damaged = new PanelOffset(new Store({ [a.key]: "{not json" })).value;
const wrong = new PanelOffset(new Store({ [a.key]: "[1, \\"x\\", 3]" })).value;
let unknown = null;
try { a.step("sideways"); } catch (err) { unknown = String(err.message); }
const base = quadVertices([1.0, 0.0, 1.2], 0.5, 0.3, [0, 0, 0]);
const shifted = quadVertices([1.0, 0.0, 1.2], 0.5, 0.3, moved);
a.reset();
console.log(JSON.stringify({ fresh, moved, stored, reloaded, far: far.value,
  damaged, wrong, unknown, base: Array.from(base), shifted: Array.from(shifted),
  reset: new PanelOffset(new Store(items)).value }));
"""


@pytest.mark.skipif(NODE is None, reason="node not installed (make sysdeps installs nodejs)")
def test_the_pages_panel_offset_steps_persists_and_moves_the_quads(tmp_path):
    static = Path(STATIC_DIR)
    script = tmp_path / "offset.mjs"
    script.write_text(
        _NODE_SCRIPT
        % {
            "offset": json.dumps((static / "panel_offset.js").as_uri()),
            "quad": json.dumps((static / "camera_quad.js").as_uri()),
        }
    )
    result = subprocess.run([NODE, str(script)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    assert out["fresh"] == [0, 0, 0]
    # right: the operator's right, world -y; up: +z; nearer: world -x (towards the operator)
    np.testing.assert_allclose(out["moved"], [-0.1, -0.2, 0.1], atol=1e-9)
    np.testing.assert_allclose(out["reloaded"], out["moved"], atol=1e-9)  # kept in localStorage
    assert json.loads(out["stored"]) == pytest.approx(out["moved"])
    assert max(abs(v) for v in out["far"]) <= 3.0 + 1e-9  # clamped
    assert out["damaged"] == [0, 0, 0] and out["wrong"] == [0, 0, 0]  # a bad stored value: none
    assert "right, left, up, down, nearer, farther" in out["unknown"]
    base = np.array(out["base"]).reshape(4, 5)
    shifted = np.array(out["shifted"]).reshape(4, 5)
    # the page's XR frame is Y up, -Z forward: world (x, y, z) -> (-y, z, -x)
    np.testing.assert_allclose(shifted[:, :3] - base[:, :3], [[0.2, 0.1, 0.1]] * 4, atol=1e-6)
    np.testing.assert_array_equal(shifted[:, 3:], base[:, 3:])  # the same image corners
    assert out["reset"] == [0, 0, 0]
