"""The WebXR source in a real browser: a live ``teleop --task pour --source webxr`` session and
Debian's headless chromium on its page, with Meta's Immersive Web Emulation Runtime (iwer,
from npm, injected by this test only) emulating a Quest 3 in hand-tracking mode.

Checks that the page loads, draws the twin's meshes (and a damaged mesh as its box, without
an error) and Start opens an immersive session, that the server receives frames of both hands, that moving the emulated right hand moves the twin's arm target and its
arm, that the page's Pause / Resume pause the operator, and that closing the page leaves the
robot holding (tracking lost). A screenshot goes to ``test-artifacts/webxr/``.

Skips when playwright, chromium or npm is missing, or when ``npm install iwer`` fails (it
installs once into ``~/.cache/beavr_sim/iwer``, ``BEAVR_IWER_DIR`` to move it).
"""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright (extra 'dev') not installed: pip install playwright"
)

from beavr_sim.bench.webxr import (  # noqa: E402
    CHROMIUM_ARGS,
    IWER_SETUP,
    SessionThread,
    ensure_iwer,
    find_chromium,
)

CHROMIUM = find_chromium()
if CHROMIUM is None:
    pytest.skip(
        "chromium not found: sudo apt-get install chromium (or set BEAVR_CHROMIUM)",
        allow_module_level=True,
    )

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts" / "webxr"


@pytest.fixture(scope="module")
def iwer_bundle() -> Path:
    try:
        return ensure_iwer()
    except RuntimeError as exc:
        pytest.skip(f"iwer (the WebXR emulator, from npm) is not available: {exc}")


class _Frames:
    """A tick listener: the sides of the well-tracked hand frames the loop used."""

    def __init__(self):
        self.sides: set[str] = set()

    def __call__(self, tick) -> None:
        self.sides.update(f.side for f in tick.frames if f.tracked.sum() >= 20)


def _wait_for(page, script: str, timeout_s: float, what: str) -> None:
    """Polls ``script`` (an expression) in the page: its CSP forbids the eval that
    ``page.wait_for_function`` falls back to while it polls."""
    end = time.monotonic() + timeout_s
    while not page.evaluate(script):
        if time.monotonic() > end:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.05)


SCENE_STATUS = "document.getElementById('scene-status').textContent"


def _target(sess) -> np.ndarray | None:
    T = sess.loop.operator.targets()["right"].T_world_target
    return None if T is None else T[:3, 3].copy()


def _settled(sess, moved, timeout_s: float = 30.0) -> None:
    """Wait until ``moved()`` holds and the arm target has stopped moving (the same over two
    polls 0.2 s apart): the hand's last frames have arrived and been applied."""
    end = time.monotonic() + timeout_s
    previous = None
    while True:
        now = _target(sess)
        if previous is not None and np.linalg.norm(now - previous) < 1e-4 and moved():
            return
        assert time.monotonic() < end, "the arm target never settled after the hand's move"
        previous = now
        time.sleep(0.2)


@contextmanager
def _page():
    """A headless chromium page (640x360) and the list its page errors are collected in."""
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 640, "height": 360})
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            yield page, errors
        finally:
            browser.close()


def test_emulated_quest3_drives_the_twin_and_holds_when_the_page_closes(iwer_bundle):
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.wire.ports import free_tcp_ports

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    options = SessionOptions(
        task="pour",
        source="webxr",
        viser=False,
        progress=False,
        webxr_port=free_tcp_ports(1)[0],
        token="browser-T0ken",  # required: the page must pass the printed URL's token on
    )
    assert options.webxr_config().host == "127.0.0.1" and not options.webxr_config().use_tls
    sess = SessionThread(options)
    frames = _Frames()
    sess.loop.listeners.append(frames)
    server = sess.server
    arm = sess.loop.twin.slices["right"]
    try:
        with _page() as (page, errors):
            page.add_init_script(path=str(iwer_bundle))
            page.add_init_script(script=IWER_SETUP)
            assert server.url.endswith("/?token=browser-T0ken")
            page.goto(server.url)

            # (a) The page loads, connects and gets the twin with every mesh; Start opens
            # the session.
            _wait_for(page, f"{SCENE_STATUS}.includes('meshes')", 30, "the twin's meshes")
            scene = page.evaluate(SCENE_STATUS)
            assert " 0 meshes" not in scene and "could not be read" not in scene, scene
            start = page.get_by_role("button", name="Start")
            page.wait_for_function("!document.getElementById('start').disabled", timeout=30_000)
            start.click()
            sess.wait_for(lambda: server.stats.sessions_started == 1, 20, "XR session")
            page.wait_for_function(
                "document.getElementById('status').textContent.includes('in session')",
                timeout=10_000,
            )

            # (b) Frames of both hands arrive and pass the validator.
            sess.wait_for(lambda: frames.sides == {"left", "right"}, 30, "both hands")
            sess.wait_for(lambda: _target(sess) is not None, 30, "the arm target anchored")
            assert not server.stats.rejected, server.stats.rejected
            assert sess.loop.validator.rejected == 0, sess.loop.validator.rejected_by_reason

            # (c) Moving the emulated right hand 10 cm moves the arm target 10 cm (relative
            # motion at scale 1, in the hand frame anchored at the start: the direction in
            # the world depends on the robot hand's pose then), the arm with it, and moving
            # the hand back brings the target back.
            _settled(sess, lambda: True)
            target0, q0 = _target(sess), sess.loop.twin.action[arm].copy()
            page.evaluate("window.__moveHand('right', 0, 0.10, 0, 1.5)")  # awaits the move
            _settled(sess, lambda: np.abs(sess.loop.twin.action[arm] - q0).max() > 0.02)
            target1, q1 = _target(sess), sess.loop.twin.action[arm].copy()
            moved = np.linalg.norm(target1 - target0)
            assert 0.07 < moved < 0.12, f"arm target moved {moved:.3f} m for a 0.10 m hand move"
            assert np.abs(q1 - q0).max() > 0.02, "the arm did not follow its target"
            page.screenshot(path=ARTIFACTS / "1_in_session.png")
            page.evaluate("window.__moveHand('right', 0, -0.10, 0, 1.5)")
            _settled(sess, lambda: np.linalg.norm(_target(sess) - target1) > 0.05)
            back = np.linalg.norm(_target(sess) - target0)
            assert back < 0.02, f"hand back at the start, target {back:.3f} m from its start"

            # (d) The page's Pause holds the operator (the pause flag of every frame);
            # Resume releases it.
            page.get_by_role("button", name="Pause").dispatch_event("click")
            sess.wait_for(lambda: sess.loop.operator.paused, 5, "pause")
            page.get_by_role("button", name="Resume").dispatch_event("click")
            sess.wait_for(lambda: not sess.loop.operator.paused, 5, "resume")
            assert not errors, errors

            # (e) Closing the page: no frames, the right arm holds (tracking lost).
            lost0 = sess.loop.holds.get("right", {}).get("tracking_lost", 0)
            page.close()
            sess.wait_for(  # the right hand's hold has begun
                lambda: sess.loop.holds.get("right", {}).get("tracking_lost", 0) > lost0 + 2,
                30,
                "tracking lost",
            )
            q_closed = sess.loop.twin.action[arm].copy()
            time.sleep(0.5)
            np.testing.assert_array_equal(sess.loop.twin.action[arm], q_closed)
            lost1 = sess.loop.holds.get("right", {}).get("tracking_lost", 0)
            assert lost1 > lost0 + 5, (lost0, lost1)
            assert not server.driving
    finally:
        sess.stop()
    assert sess.error is None, sess.error
    assert server.stats.hand_messages > 30


def test_page_draws_the_meshes_and_a_damaged_one_as_its_box():
    """No session: the page alone, given a scene whose first mesh is cut short."""
    import gymnasium as gym

    import beavr_sim  # noqa: F401
    from beavr_sim.headset.webxr_scene import TwinGeometry
    from beavr_sim.headset.webxr_server import WebXRConfig, WebXRServer

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    env = gym.make("beavr_sim/Pour-v0").unwrapped
    env.reset(seed=0)
    message = TwinGeometry.from_model(env.render_model).scene_message(env.data, task="Pour")
    env.close()
    meshes = message["meshes"]
    damaged = meshes[0]["name"]
    meshes[0] = {**meshes[0], "data": meshes[0]["data"][:-8]}
    server = WebXRServer(WebXRConfig(port=0))
    try:
        server.publish("scene", message)
        with _page() as (page, errors):
            page.on("console", lambda m: m.type == "error" and errors.append(m.text))
            page.goto(server.url)
            _wait_for(page, f"{SCENE_STATUS}.includes('meshes')", 30, "the twin's meshes")
            scene = page.evaluate(SCENE_STATUS)
            assert f"{len(meshes) - 1} meshes" in scene, scene
            assert f"1 could not be read, drawn as boxes: {damaged}:" in scene, scene
            page.evaluate("document.getElementById('overlay').style.display = 'none'")
            page.wait_for_timeout(300)
            page.screenshot(path=ARTIFACTS / "0_preview_damaged_mesh.png")
            assert not errors, errors
    finally:
        server.close()


def test_page_shows_the_streamed_camera_as_a_quad_in_the_scene():
    """No session: the page alone, given camera messages (a magenta image) as the camera
    stream sends them; the quad is drawn in the page's view of the scene."""
    from beavr_sim.cameras.headset_panels import WebXRCameraSink
    from beavr_sim.cameras.stream import LIVE, StreamFrame
    from beavr_sim.headset.webxr_server import WebXRConfig, WebXRServer

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    magenta = np.zeros((48, 64, 3), np.uint8)
    magenta[..., 0] = magenta[..., 2] = 255
    server = WebXRServer(WebXRConfig(port=0))
    sink = WebXRCameraSink(server)
    status = "document.getElementById('camera-status').textContent"
    try:
        with _page() as (page, errors):
            page.on("console", lambda m: m.type == "error" and errors.append(m.text))
            page.goto(server.url)
            end, seq = time.monotonic() + 30, 0
            while "in the scene: front" not in page.evaluate(status):
                assert time.monotonic() < end, "the camera quad never showed"
                seq += 1
                sink(StreamFrame("front", magenta, LIVE, 0.01, seq))
                time.sleep(0.1)
            page.evaluate("document.getElementById('overlay').style.display = 'none'")
            page.wait_for_timeout(300)
            shot = ARTIFACTS / "2_camera_quad.png"
            page.screenshot(path=shot)
            for _ in range(3):  # the user moves the panel up 0.3 m with the page's buttons
                page.evaluate("document.querySelector('#panel-move [data-move=up]').click()")
            page.evaluate(
                "new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))"
            )
            moved = ARTIFACTS / "3_camera_quad_moved.png"
            page.screenshot(path=moved)
            stored = page.evaluate("localStorage.getItem('beavr_sim.cameraPanelOffset')")
            assert not errors, errors
    finally:
        server.close()
    from PIL import Image

    rows = []
    for path in (shot, moved):
        pixels = np.asarray(Image.open(path).convert("RGB")).astype(int)
        is_magenta = (pixels[..., 0] > 200) & (pixels[..., 2] > 200) & (pixels[..., 1] < 80)
        assert is_magenta.sum() > 200, f"no magenta quad in the page's view ({path.name})"
        rows.append(np.nonzero(is_magenta)[0].mean())
    assert rows[1] < rows[0] - 10, rows  # drawn higher in the view
    assert json.loads(stored) == [0, 0, 0.3]  # kept in the page's localStorage
