"""The real-camera stream: panels reach a viser client, a WebXR page and the Quest image socket
off the control thread; a slow viewer never holds the control loop (newest grab only, older
ones dropped); a dead or too-old camera is shown as NO SIGNAL, never its last frame."""

from __future__ import annotations

import base64
import io
import json
import socket
import threading
import time
from urllib.parse import urlsplit, urlunsplit

import numpy as np
import pytest
import zmq
from PIL import Image

from beavr_sim.cameras.real import Grab
from beavr_sim.cameras.stream import (
    LIVE,
    NO_SIGNAL,
    CameraStream,
    StreamConfig,
    compose,
)

WAIT_S = 20.0  # readiness deadline, never a pass/fail timing bound
SHAPE = (48, 64, 3)


def _real(value: int = 200) -> np.ndarray:
    return np.full(SHAPE, value, np.uint8)


def _live(value: int = 200, age_s: float = 0.01) -> Grab:
    return Grab(frames={"front": _real(value)}, ages_s={"front": age_s}, dead=())


DEAD = Grab(frames={}, ages_s={}, dead=("front",))


class _Collect:
    def __init__(self) -> None:
        self.frames = []
        self.arrived = threading.Event()

    def __call__(self, frame) -> None:
        self.frames.append(frame)
        self.arrived.set()

    def wait(self, n: int):
        deadline = time.monotonic() + WAIT_S
        while len(self.frames) < n:
            assert time.monotonic() < deadline, f"fewer than {n} panels arrived"
            self.arrived.wait(0.05)
            self.arrived.clear()
        return self.frames


def _stream(*sinks, rate_hz: float = 100.0, **kw) -> CameraStream:
    return CameraStream(StreamConfig(rate_hz=rate_hz, **kw), list(sinks), {"front": SHAPE})


# --- composing and dead cameras ---------------------------------------------------------------


def test_views_compose_real_twin_both_and_the_blend():
    real, twin = _real(200), np.full((24, 32, 3), 100, np.uint8)  # the twin at half size
    assert compose(real, twin, "real", 0.5) is real
    assert compose(real, twin, "twin", 0.5).shape == SHAPE
    assert compose(real, twin, "both", 0.5).shape == (48, 128, 3)
    np.testing.assert_allclose(compose(real, twin, "overlay", 0.25), 175, atol=1)
    assert compose(real, None, "overlay", 0.5) is real  # no twin render: the real frame
    with pytest.raises(ValueError, match="real, twin, both, overlay"):
        StreamConfig(view="side")
    with pytest.raises(ValueError, match="blend"):
        StreamConfig(blend=1.5)


def test_a_dead_or_too_old_camera_is_no_signal_never_its_last_frame():
    stream = _stream(rate_hz=0)  # off: panels composed by hand
    live = stream.panels(_live(200), None, time.perf_counter())[0]
    assert live.state == LIVE and live.age_s is not None and "age" in live.label
    for grab in (DEAD, _live(200, age_s=5.0)):
        panel = stream.panels(grab, None, time.perf_counter())[0]
        assert panel.state == NO_SIGNAL and panel.age_s is None
        assert "NO SIGNAL" in panel.label
        assert not np.array_equal(panel.image, live.image)  # not the last live frame
    assert stream.no_signal == 2


def test_a_slow_viewer_never_holds_the_control_loop():
    release = threading.Event()
    shown = []

    def slow_sink(frame) -> None:
        shown.append(frame)
        release.wait(WAIT_S)

    stream = _stream(slow_sink)
    ticks, n = [0], 2000

    def control_loop() -> None:
        for i in range(n):
            stream.offer(_live(i % 250))
            ticks[0] += 1

    loop = threading.Thread(target=control_loop)
    loop.start()
    loop.join(WAIT_S)
    try:
        assert not loop.is_alive(), "the control loop waited on a slow viewer"
        assert ticks[0] == n and stream.offered == n
        assert stream.dropped >= n - 2  # one in the mailbox, maybe one taken: nothing queued
    finally:
        release.set()
        stream.close()
    assert len(shown) <= 3


# --- the viewers ------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _viser_messages(ws):
    """Decompressed msgpack parts of viser's wire messages (its hybrid zstd format)."""
    import zstandard

    raw = ws.recv(timeout=WAIT_S)
    inner, size = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    return zstandard.ZstdDecompressor().decompress(raw[16 : 16 + size], max_output_size=inner)


def test_panels_reach_a_viser_client_and_a_dead_camera_reads_no_signal():
    viser = pytest.importorskip("viser", reason="viser (extra 'viz') not installed")
    from websockets.sync.client import connect

    from beavr_sim.viz.camera_panel import CameraPanel

    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    panel = CameraPanel(server.gui, {"front": SHAPE})
    stream = _stream(panel, rate_hz=50.0)
    panel.attach(stream)
    try:
        url = f"ws://127.0.0.1:{server.get_port()}"
        with connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:

            def until(text: bytes, grab) -> None:
                deadline = time.monotonic() + WAIT_S
                while time.monotonic() < deadline:
                    stream.offer(grab)
                    if text in _viser_messages(ws):
                        return
                raise AssertionError(f"{text!r} never reached the viser client")

            until(b"front: live, age", _live())
            until(b"front: NO SIGNAL**", DEAD)
        panel.view.value = "overlay"  # the panel's controls set the stream's view and blend
        panel.blend.value = 0.25
        assert stream.view == "overlay" and stream.blend == 0.25
    finally:
        stream.close()
        server.stop()


def test_panels_reach_a_webxr_page_with_their_age_or_no_signal():
    from websockets.sync.client import connect

    from beavr_sim.cameras.headset_panels import WebXRCameraSink
    from beavr_sim.headset.webxr_server import WebXRConfig, WebXRServer

    server = WebXRServer(WebXRConfig(port=0))
    stream = _stream(WebXRCameraSink(server), rate_hz=50.0)
    parts = urlsplit(server.url)
    url = urlunsplit(("ws", parts.netloc, "/ws", parts.query, ""))
    try:
        with connect(url, max_size=None) as ws:

            def until(state: str, grab) -> dict:
                deadline = time.monotonic() + WAIT_S
                while time.monotonic() < deadline:
                    stream.offer(grab)
                    msg = json.loads(ws.recv(timeout=WAIT_S))
                    if msg.get("type") == "camera" and msg["state"] == state:
                        return msg
                raise AssertionError(f"no {state} camera message reached the page")

            live = until(LIVE, _live(200))
            assert live["name"] == "front" and live["age_ms"] is not None
            image = np.asarray(Image.open(io.BytesIO(base64.b64decode(live["jpeg"]))))
            assert image.shape == SHAPE and abs(float(image.mean()) - 200) < 5
            dead = until(NO_SIGNAL, DEAD)
            assert dead["age_ms"] is None and "NO SIGNAL" in dead["label"]
    finally:
        stream.close()
        server.close()


def test_panels_reach_the_quest_camera_socket():
    from beavr_sim.cameras.headset_panels import QuestCameraSink
    from beavr_sim.headset.quest_io import HeadsetImagePublisher
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    context = zmq.Context()
    config = TransportConfig(ports=PortConfig.free())
    publisher = HeadsetImagePublisher(context, config, rate_hz=100.0)
    stream = _stream(QuestCameraSink(publisher, ("front",)), rate_hz=50.0)
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(config.endpoint("headset_camera", bind=False))
    try:
        deadline, received = time.monotonic() + WAIT_S, None
        while received is None and time.monotonic() < deadline:
            stream.offer(_live(120))  # slow joiner: keep offering until subscribed
            if sub.poll(20):
                received = sub.recv()
        assert received is not None and received[:2] == b"\xff\xd8"
        assert np.asarray(Image.open(io.BytesIO(received))).shape == SHAPE
    finally:
        stream.close()
        sub.close(linger=0)
        publisher.close()
        context.destroy(linger=0)


def test_nothing_offered_for_a_while_turns_the_panel_to_no_signal():
    seen = _Collect()
    stream = _stream(seen, rate_hz=50.0, dead_after_s=0.05)
    try:
        stream.offer(_live())
        frames = seen.wait(2)  # the live panel, then NO SIGNAL once nothing more arrives
        assert frames[0].state == LIVE
        assert frames[-1].state == NO_SIGNAL
    finally:
        stream.close()


# --- the twin's renders -----------------------------------------------------------------------


class _Twin:
    """A TwinSource: renders of a fixed level, an age, the threads it ran on."""

    def __init__(self, level: int = 60, age_s: float | None = 0.02, own: tuple = ("front",)):
        self.level, self.age_s, self.own = level, age_s, own
        self.threads: set[str] = set()
        self.closed_on: str | None = None
        self.asked: list[tuple[str, ...]] = []

    def render(self, shapes):
        self.threads.add(threading.current_thread().name)
        self.asked.append(tuple(shapes))
        if self.age_s is None:
            return {}, None
        return {n: np.full((24, 32, 3), self.level, np.uint8) for n in shapes}, self.age_s

    def camera_for(self, panel: str) -> str:
        return panel if panel in self.own else "front"

    def panel_shape(self, panel: str):
        return SHAPE

    def close(self) -> None:
        self.closed_on = threading.current_thread().name


def test_the_twin_source_feeds_every_view_and_a_stale_twin_is_no_signal():
    twin = _Twin()
    stream = CameraStream(StreamConfig(rate_hz=0, view="auto"), [], {"front": SHAPE}, twin=twin)
    assert stream.view == "both"  # auto: the twin has a camera of the real camera's name
    now = time.perf_counter
    stream.set_view("real")
    (panel,) = stream.panels(_live(200), None, now())
    assert panel.state == LIVE and panel.image.mean() == 200 and panel.note == ""
    assert twin.asked == []  # the real view renders nothing
    stream.set_view("twin")
    (panel,) = stream.panels(_live(200), None, now())
    assert panel.state == LIVE and panel.image.shape == SHAPE and panel.image.mean() == 60
    assert panel.age_s == pytest.approx(0.02) and panel.label.endswith("(twin)")
    stream.set_view("both")
    (panel,) = stream.panels(_live(200), None, now())
    assert panel.image.shape == (48, 128, 3)
    assert panel.image[:, :64].mean() == 200 and panel.image[:, 64:].mean() == 60
    stream.set_view("overlay")
    stream.set_blend(0.25)
    (panel,) = stream.panels(_live(200), None, now())
    np.testing.assert_allclose(panel.image, 165, atol=1)  # 0.25 * 60 + 0.75 * 200
    (panel,) = stream.panels(DEAD, None, now())  # the real camera dead: never the twin alone
    assert panel.state == NO_SIGNAL and panel.age_s is None

    for age in (None, 5.0):  # no twin pose yet, or the twin stopped ticking
        twin.age_s = age
        stream.set_view("twin")
        (panel,) = stream.panels(_live(200), None, now())
        assert panel.state == NO_SIGNAL and panel.image.mean() != 60
        stream.set_view("overlay")
        (panel,) = stream.panels(_live(200), None, now())
        assert panel.state == LIVE and panel.image.mean() == 200  # the real frame alone...
        assert "twin NO SIGNAL" in panel.label  # ...saying so


def test_twin_only_panels_render_on_the_stream_thread_at_the_rate():
    twin = _Twin(own=("side",))
    seen = _Collect()
    stream = CameraStream(
        StreamConfig(rate_hz=50.0, view="auto"), [seen], {"side": SHAPE}, twin=twin, real=()
    )
    assert stream.view == "real"  # auto: no real camera has a twin of its name
    try:
        frames = seen.wait(3)  # no real camera, nothing offered: the twin drives the panels
    finally:
        stream.close()
    assert all(f.state == LIVE and f.image.mean() == 60 for f in frames)
    assert twin.threads == {"camera-stream"} and twin.closed_on == "camera-stream"


class _Panel(_Collect):
    """A browser view's camera panel stand-in: collects what the stream sends it."""

    def attach(self, stream) -> None:
        self.stream = stream


class _View:
    def __init__(self) -> None:
        self.panel = _Panel()

    def add_camera_panel(self, shapes):
        self.shapes = dict(shapes)
        return self.panel


def test_the_twin_process_streams_its_renders_to_the_view_from_its_steps():
    """--camera-stream-hz --multiprocess (main refused it): the twin process's stream (as
    twin_main attaches it) renders the twin's camera from the poses its stage's steps copy, and
    the browser view's panel gets them live."""
    from beavr_sim.teleop.process_config import TwinProcessConfig
    from beavr_sim.teleop.stages import TwinStage
    from beavr_sim.teleop.twin_camera_stream import TwinCameraStream, attach_camera_stream
    from beavr_sim.teleop.twin_process import make_twin_env
    from beavr_sim.twin.twin import TwinInterface

    env = make_twin_env(TwinProcessConfig(task="PickupBox", embodiment="rx1", control_hz=30.0))
    twin = TwinInterface(env)
    twin.reset(0)
    stage = TwinStage(twin)
    view = _View()
    close = attach_camera_stream(TwinCameraStream(StreamConfig(20.0)), env, stage, None, view=view)
    try:
        deadline = time.monotonic() + WAIT_S
        # The stream renders what the steps copied: a round before the first step's copy has
        # no pose to draw (NO SIGNAL), as has one rendered over dead_after_s after its copy (a
        # busy machine can stall this thread's steps that long).
        while sum(f.state == LIVE for f in view.panel.frames) < 2:
            assert time.monotonic() < deadline, "no live panel reached the view"
            stage.step()
            view.panel.arrived.wait(0.02)
    finally:
        close()
        env.close()
    frames = view.panel.frames
    assert view.panel.stream is not None and list(view.shapes) == [frames[0].name]
    live = [f for f in frames if f.state == LIVE]
    assert len(live) >= 2 and all(f.image.std() > 0 and f.age_s is not None for f in live)


class _QuestPublisher:
    """A ``HeadsetImagePublisher`` stand-in: keeps the JPEG bytes it would send."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def publish(self, image) -> bool:
        from beavr_sim.headset.quest_io import encode_jpeg

        self.sent.append(encode_jpeg(image, 90))
        return True


class _RealCameras:
    """A connected ``RealCameras`` stand-in: one live ``front`` camera."""

    cameras = names = ("front",)
    depth_cameras = ()

    def frame_shape(self, name):
        return SHAPE

    def peek(self):
        return _live(200)


@pytest.mark.parametrize(
    ("view", "shape", "left", "right"),
    [("real", SHAPE, 200, 200), ("twin", SHAPE, 60, 60), ("both", (48, 128, 3), 200, 60),
     ("overlay", SHAPE, 165, 165)],
)  # fmt: skip
def test_the_quest_panel_shows_the_view_the_user_chose(view, shape, left, right):
    """The Quest app's camera panel is the stream's composed panel (one compositor): its JPEG
    decodes to the view's image, the twin's render beside or over the real frame."""
    from beavr_sim.teleop.camera_viewers import CameraViewers, start_camera_stream

    quest = _QuestPublisher()
    config = StreamConfig(rate_hz=50.0, view=view, blend=0.25)
    stream = start_camera_stream(_RealCameras(), config, CameraViewers(quest=quest, twin=_Twin()))
    try:
        deadline = time.monotonic() + WAIT_S
        while not quest.sent:
            assert time.monotonic() < deadline, "no panel reached the Quest publisher"
            time.sleep(0.01)
    finally:
        stream.close()
    image = np.asarray(Image.open(io.BytesIO(quest.sent[0])))
    assert image.shape == shape
    half = shape[1] // 2
    assert abs(float(image[:, :half].mean()) - left) < 4
    assert abs(float(image[:, half:].mean()) - right) < 4


def test_the_twin_process_quest_panel_never_doubles_the_headset_images(monkeypatch):
    """--multiprocess without a real camera: the Quest socket keeps the twin's headset images
    alone (the twin process renders them there); the stream sends it nothing of its own."""
    import beavr_sim.teleop.twin_camera_stream as twin_camera_stream

    monkeypatch.setattr(twin_camera_stream, "twin_feed", lambda *a: (_Twin(), ("front",)))
    quest, view = _QuestPublisher(), _View()

    class _Stage:
        after_step: list = []

    config = twin_camera_stream.TwinCameraStream(StreamConfig(50.0), quest=True)
    close = twin_camera_stream.attach_camera_stream(
        config, None, _Stage(), None, view=view, quest=quest
    )
    try:
        view.panel.wait(2)  # the stream runs (its twin-only panel reaches the browser view)
    finally:
        close()
    assert quest.sent == []
