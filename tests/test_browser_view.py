"""The browser view in a real browser: Debian's chromium (headless, software WebGL) driven by
playwright against a live teleop session replaying a bundled trace in real time.

Checks that the scene renders and moves, that the page's Pause holds the robot, Resume moves
it again and Reset restarts the episode from home. Screenshots go to
``test-artifacts/browser/``. Skips when playwright or chromium is missing (``make test`` as
root installs both; never ``playwright install``).
"""

from __future__ import annotations

import io
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser", reason="viser (extra 'viz') not installed")
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright (extra 'dev') not installed: pip install playwright"
)

# The chromium search and its headless-WebGL flags (SwiftShader through ANGLE) are shared with
# the WebXR browser test and benchmark.
from beavr_sim.bench.webxr import CHROMIUM_ARGS, find_chromium  # noqa: E402

CHROMIUM = find_chromium()
if CHROMIUM is None:
    pytest.skip(
        "chromium not found: sudo apt-get install chromium (or set BEAVR_CHROMIUM)",
        allow_module_level=True,
    )

from beavr_sim.teleop.pipeline import StopTeleop  # noqa: E402

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts" / "browser"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Stop(StopTeleop):
    pass


class _Probe:
    """A loop listener: the twin's latest state, the state right after each reset; raises
    :class:`_Stop` (ending the session) once asked to."""

    def __init__(self):
        self.last = None  # (wall time, t, positions)
        self.after_reset = None  # (t, positions) of the first tick of a restarted episode
        self.resets = 0  # episode restarts seen (a trace replayed with --repeat restarts)
        self.action = None  # the latest commanded joint targets
        self.stop = threading.Event()

    def __call__(self, tick) -> None:
        if self.stop.is_set():
            raise _Stop
        if self.last is not None and tick.state.t < self.last[1] - 1e-9:
            self.after_reset = (tick.state.t, tick.state.positions.copy())
            self.resets += 1
        self.last = (time.monotonic(), tick.state.t, tick.state.positions.copy())
        self.action = tick.state.action.copy()


class _Session:
    """``python -m beavr_sim.teleop --task pick_place --source trace --headless --repeat 0
    --viser-port P`` in a background thread, with a probe on its loop."""

    def __init__(self, monkeypatch):
        from beavr_sim.teleop import session

        self.port = _free_port()
        self.probe = _Probe()
        self.loop = None
        self.error: BaseException | None = None
        build = session.build_loop

        def build_loop(options, context=None):
            loop = build(options, context)
            loop.listeners.append(self.probe)
            self.loop = loop
            return loop

        monkeypatch.setattr(session, "build_loop", build_loop)
        options = session.SessionOptions(
            task="pick_place",
            source="trace",
            headless=True,
            viser_port=self.port,
            repeat=0,
            progress=False,
        )
        assert options.clock == "real" and options.viser_host == "127.0.0.1"

        def run():
            try:
                session.run_session(options)
            except _Stop:
                pass
            except BaseException as e:  # surfaced by the test
                self.error = e

        self.thread = threading.Thread(target=run, name="teleop-session", daemon=True)
        self.thread.start()
        self.wait_for(lambda: self.view is not None and self.probe.last is not None, 60, "start")

    @property
    def view(self):
        from beavr_sim.teleop.view import ViewListener

        if self.loop is None:
            return None
        return next((x.view for x in self.loop.listeners if isinstance(x, ViewListener)), None)

    def wait_for(self, cond, timeout: float, what: str) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if self.error is not None:
                raise self.error
            if time.monotonic() > end:
                raise AssertionError(f"timed out waiting for {what}")
            time.sleep(0.05)

    @property
    def arm_joints(self) -> np.ndarray:
        """Indices (action order) of the arm joints."""
        names = self.loop.twin.env.joints.names
        return np.array([i for i, n in enumerate(names) if "/joint" in n])

    def positions_over(self, seconds: float, joints=slice(None)) -> float:
        """Largest change (rad) of ``joints`` over ``seconds`` of wall time."""
        q0 = self.probe.last[2]
        time.sleep(seconds)
        return float(np.abs(self.probe.last[2] - q0)[joints].max())

    def held_over(self, seconds: float, tries: int = 3, joints=slice(None)) -> float:
        """:meth:`positions_over` within one episode: a window in which the trace ended and
        the session restarted it (``--repeat``, the robot re-homes) is measured again."""
        for _ in range(tries):
            resets = self.probe.resets
            change = self.positions_over(seconds, joints)
            if self.probe.resets == resets:
                return change
        raise AssertionError("the episode restarted in every measurement window")

    def close(self) -> None:
        self.probe.stop.set()
        self.thread.join(15)


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def test_browser_view_renders_pauses_resumes_and_resets(monkeypatch):
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    sess = _Session(monkeypatch)
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(
                executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS
            )
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(sess.view.url)
                page.wait_for_selector("canvas", timeout=30_000)
                pause = page.get_by_role("button", name="Pause")
                pause.wait_for(timeout=30_000)
                page.wait_for_timeout(2500)  # the scene arrives, the first frames render
                close = page.locator(".mantine-Notification-closeButton")
                if close.count():  # "software WebGL" notice: out of the screenshots
                    close.first.click()

                # (a) the scene renders and moves while the trace plays.
                shot1 = page.screenshot(path=ARTIFACTS / "1_running.png")
                page.wait_for_timeout(1000)
                shot2 = page.screenshot(path=ARTIFACTS / "2_running_1s_later.png")
                a, b = _pixels(shot1), _pixels(shot2)
                assert a.std() > 10, "blank page: the canvas did not render"
                changed = (np.abs(a - b).max(axis=2) > 16).mean()
                assert changed > 1e-4, f"nothing moved on the page ({changed:.2e} of pixels)"

                # (b) Pause in the page holds the robot.
                pause.click()
                sess.wait_for(lambda: sess.loop.operator.paused, 10, "pause")
                sess.wait_for(  # the held targets settle
                    lambda: sess.positions_over(0.2, joints=sess.arm_joints) < 5e-4, 30, "settle"
                )
                action, resets = sess.probe.action, sess.probe.resets
                held = sess.held_over(1.0, joints=sess.arm_joints)
                # No new command while paused; the arm stands still. (Fingers closed on an
                # object may still settle against it, so the measured check is on the arm.)
                if sess.probe.resets == resets:
                    np.testing.assert_array_equal(sess.probe.action, action)
                assert held < 2e-3, f"paused arm moved {held:.4f} rad"
                resume = page.get_by_role("button", name="Resume")
                resume.wait_for(timeout=10_000)
                page.screenshot(path=ARTIFACTS / "3_paused.png")

                # (c) Resume: it moves again.
                resume.click()
                sess.wait_for(lambda: not sess.loop.operator.paused, 10, "resume")
                moved = 0.0  # the largest change over up to four 1 s windows
                for _ in range(4):
                    moved = max(moved, sess.positions_over(1.0))
                    if moved > 1e-2:
                        break
                assert moved > 1e-2, f"resumed robot moved only {moved:.4f} rad"

                # (d) Reset: the episode restarts from home. Clicked once the episode is past
                # 0.5 s, so a restart of the trace's own (--repeat) just before the click cannot
                # pass for this one.
                sess.wait_for(lambda: sess.probe.last[1] > 0.5, 30, "the episode past 0.5 s")
                t_before = sess.probe.last[1]
                sess.probe.after_reset = None  # only the restart this click causes counts
                page.get_by_role("button", name="Reset").click()
                sess.wait_for(lambda: sess.probe.after_reset is not None, 10, "reset")
                t_reset, q_reset = sess.probe.after_reset
                assert t_reset < min(t_before, 0.5)
                home = sess.loop.twin.env.joints.home
                assert np.abs(q_reset - home).max() < 0.05
                page.wait_for_timeout(1500)
                page.screenshot(path=ARTIFACTS / "4_after_reset.png")
            finally:
                browser.close()
    finally:
        sess.close()
    assert sess.error is None
