"""``python -m beavr_sim.bench.webxr``: the WebXR source driven by an emulated headset.

A live ``teleop --source webxr`` session (one process, real clock) and Debian's headless
chromium on its page, with Meta's Immersive Web Emulation Runtime (``iwer``, npm) injected
before the page loads, emulating a Quest 3 in hand-tracking mode; the emulated right hand
moves on a slow circle. Measured:

- frames per second the server received (``hands`` messages; each carries both hands);
- page -> command latency: from the XR frame's time on the page (``performance.timeOrigin``
  + the frame time) to the moment the twin applied the command made from that frame (wall
  clock: same machine, same clock);
- server -> command: from the message's receipt to the command applied (the loop's own
  latency, ``time.monotonic``).

    python -m beavr_sim.bench.webxr [--task pour] [--seconds 10] [--json F]

iwer is installed with ``npm install iwer`` into ``~/.cache/beavr_sim/iwer`` on first use
(``BEAVR_IWER_DIR`` to move it); never vendored. The emulation runs at the page's animation
frame rate (headless chromium: about 60 Hz) with SwiftShader for WebGL, not at a headset's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from beavr_sim.wire.ports import free_tcp_ports

IWER_VERSION = "^2.5"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-dev-shm-usage",
    "--use-angle=swiftshader",
    "--use-gl=angle",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
]

#: Runs in the page before its own scripts (test and benchmark only; the page has none of
#: it): an emulated Quest 3 in hand-tracking mode, and a helper that moves a hand smoothly.
IWER_SETUP = """
(() => {
  const device = new IWER.XRDevice(IWER.metaQuest3);
  device.installRuntime({ forceInstall: true });
  device.primaryInputMode = "hand";
  window.__iwer = device;
  // Move a hand by (dx, dy, dz) metres (WebXR axes) over `seconds`, one step per animation
  // frame. Rejects, naming how many frames came, if the page's animation frames stop for
  // 30 s beyond the move (page.evaluate has no timeout of its own).
  window.__moveHand = (side, dx, dy, dz, seconds) => new Promise((resolve, reject) => {
    const hand = device.hands[side];
    const p0 = [hand.position.x, hand.position.y, hand.position.z];
    const t0 = performance.now();
    let frames = 0;
    const guard = setTimeout(() => reject(new Error(
      `__moveHand: ${frames} animation frames in ${((performance.now() - t0) / 1000).toFixed(1)} s, ` +
      `the move not finished (the page stopped drawing)`)), (seconds + 30) * 1000);
    const step = () => {
      frames += 1;
      const a = Math.min(1, (performance.now() - t0) / (seconds * 1000));
      hand.position.set(p0[0] + a * dx, p0[1] + a * dy, p0[2] + a * dz);
      if (a < 1) requestAnimationFrame(step); else { clearTimeout(guard); resolve(); }
    };
    step();
  });
  // Circle a hand (radius r metres, period seconds) in its frontal plane until stopped.
  window.__circleHand = (side, r, period) => {
    const hand = device.hands[side];
    const c = [hand.position.x, hand.position.y, hand.position.z];
    const t0 = performance.now();
    window.__circling = true;
    const step = () => {
      const w = 2 * Math.PI * (performance.now() - t0) / (period * 1000);
      hand.position.set(c[0] + r * Math.sin(w), c[1] + r * (1 - Math.cos(w)), c[2]);
      if (window.__circling) requestAnimationFrame(step);
    };
    step();
  };
})();
"""


def iwer_dir() -> Path:
    return Path(
        os.environ.get("BEAVR_IWER_DIR") or Path.home() / ".cache" / "beavr_sim" / "iwer"
    ).expanduser()


def ensure_iwer(folder: Path | None = None) -> Path:
    """Path of iwer's browser bundle (``build/iwer.js``, a UMD defining ``IWER``), installed
    with npm into ``folder`` when missing. Raises ``RuntimeError`` saying why it cannot."""
    folder = Path(folder) if folder is not None else iwer_dir()
    bundle = folder / "node_modules" / "iwer" / "build" / "iwer.js"
    if bundle.is_file():
        return bundle
    npm = shutil.which("npm")
    if npm is None:
        raise RuntimeError("npm not found: sudo apt-get install nodejs npm (make sysdeps)")
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "package.json").is_file():
        (folder / "package.json").write_text('{"name": "beavr-sim-iwer", "private": true}\n')
    cmd = [npm, "install", "--no-audit", "--no-fund", "--loglevel=error", f"iwer@{IWER_VERSION}"]
    try:
        result = subprocess.run(
            cmd, cwd=folder, capture_output=True, text=True, timeout=300, check=False
        )
    except subprocess.TimeoutExpired:
        raise RuntimeError("npm install iwer took over 300 s (no network?)") from None
    if result.returncode != 0 or not bundle.is_file():
        raise RuntimeError(f"npm install iwer failed: {result.stderr.strip()[-500:]}")
    return bundle


def find_chromium() -> str | None:
    return (
        os.environ.get("BEAVR_CHROMIUM")
        or shutil.which("chromium")
        or shutil.which("chromium-browser")
        or next(
            (p for p in ("/usr/bin/chromium", "/usr/lib/chromium/chromium") if Path(p).exists()),
            None,
        )
    )


class SessionThread:
    """``teleop --source webxr`` (:func:`~beavr_sim.teleop.session.run_session`) in a thread;
    :attr:`loop` once built. :meth:`stop` ends it from a tick listener.

    The loop is reached through ``run_session``'s ``on_loop`` (a stop listener added)."""

    def __init__(self, options, start_timeout_s: float = 120.0):
        from beavr_sim.teleop import session  # local: heavy (the pipeline: mink, scipy)
        from beavr_sim.teleop.pipeline import StopTeleop  # local: heavy (the pipeline: mink, scipy)

        self.loop = None
        self.error: BaseException | None = None
        self.summary = None
        self._stop = threading.Event()
        self._built = threading.Event()

        class _Stop(StopTeleop):
            pass

        def stop_listener(tick) -> None:
            if self._stop.is_set():
                raise _Stop

        def on_loop(loop) -> None:
            loop.listeners.append(stop_listener)
            self.loop = loop
            self._built.set()

        def run() -> None:
            try:
                self.summary = session.run_session(options, on_loop=on_loop)
            except _Stop:
                pass
            except BaseException as exc:
                self.error = exc
            finally:
                self._built.set()

        self.thread = threading.Thread(target=run, name="teleop-session", daemon=True)
        self.thread.start()
        if not self._built.wait(start_timeout_s) or self.loop is None:
            raise RuntimeError(f"the teleop session did not start: {self.error!r}")

    @property
    def server(self):
        return self.loop.source.server

    def wait_for(self, condition, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not condition():
            if self.error is not None:
                raise RuntimeError(f"the teleop session failed: {self.error!r}") from self.error
            if time.monotonic() > end:
                raise TimeoutError(f"timed out waiting for {what}")
            time.sleep(0.05)

    def stop(self, timeout_s: float = 20.0) -> None:
        self._stop.set()
        self.thread.join(timeout_s)


class CommandLatency:
    """A command hook, one sample per hand frame and effector (the first command made from
    it): page frame time -> command applied (wall clock, ms, :attr:`page_ms`) and server
    receipt -> command applied (``time.monotonic``, :attr:`server_ms`)."""

    def __init__(self):
        self.page_ms: list[float] = []
        self.server_ms: list[float] = []
        self._last: dict[str, float] = {}

    def __call__(self, outcome, commands) -> None:
        wall, mono = time.time(), time.monotonic()
        for name in outcome.accepted:
            cmd = commands[name]
            if np.isfinite(cmd.t_source) and cmd.t_source != self._last.get(name):
                self._last[name] = cmd.t_source
                self.page_ms.append((wall - cmd.t_source) * 1e3)
                self.server_ms.append((mono - cmd.t_receive) * 1e3)


def _percentiles(values) -> dict:
    if not len(values):
        return {"n": 0}
    a = np.asarray(values)
    return {
        "n": len(a),
        "p50": round(float(np.percentile(a, 50)), 2),
        "p90": round(float(np.percentile(a, 90)), 2),
        "p99": round(float(np.percentile(a, 99)), 2),
    }


def measure(task: str = "pour", seconds: float = 10.0, screenshot: Path | None = None) -> dict:
    from playwright import sync_api

    from beavr_sim.teleop.session import SessionOptions  # local: heavy (the pipeline: mink, scipy)

    chromium = find_chromium()
    if chromium is None:
        raise RuntimeError("chromium not found: sudo apt-get install chromium")
    bundle = ensure_iwer()
    options = SessionOptions(
        task=task, source="webxr", viser=False, progress=False, webxr_port=free_tcp_ports(1)[0]
    )
    sess = SessionThread(options)
    latency = CommandLatency()
    sess.loop.command_hooks.append(latency)
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(
                executable_path=chromium, headless=True, args=CHROMIUM_ARGS
            )
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 720})
                page.add_init_script(path=str(bundle))
                page.add_init_script(script=IWER_SETUP)
                page.goto(sess.server.url)
                page.get_by_role("button", name="Start").click(timeout=30_000)
                sess.wait_for(lambda: sess.server.stats.hand_messages > 30, 30, "hand frames")
                page.evaluate("window.__circleHand('right', 0.08, 4.0)")
                time.sleep(1.0)  # the operator anchors, the filters settle
                n0, t0 = sess.server.stats.hand_messages, time.monotonic()
                k0 = len(latency.page_ms)
                time.sleep(seconds)
                n1, t1 = sess.server.stats.hand_messages, time.monotonic()
                if screenshot is not None:
                    screenshot.parent.mkdir(parents=True, exist_ok=True)
                    page.screenshot(path=str(screenshot))
                page_sent = page.evaluate("document.getElementById('stats').textContent")
            finally:
                browser.close()
        stats = sess.server.stats
        return {
            "task": task,
            "seconds": round(t1 - t0, 2),
            "frames_per_s": round((n1 - n0) / (t1 - t0), 1),
            "page_to_command_ms": _percentiles(latency.page_ms[k0:]),
            "server_to_command_ms": _percentiles(latency.server_ms[k0:]),
            "rejected": dict(stats.rejected),
            "validator_rejected": sess.loop.validator.rejected_by_reason,
            "twin_messages_sent": stats.twin_sent,
            "page": page_sent,
            "holds": {k: dict(v) for k, v in sess.loop.holds.items()},
        }
    finally:
        sess.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m beavr_sim.bench.webxr", description=__doc__)
    p.add_argument("--task", default="pour")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--json", type=Path, default=None, help="also write the result here")
    p.add_argument("--screenshot", type=Path, default=None, help="PNG of the page in session")
    args = p.parse_args(argv)
    try:
        result = measure(args.task, args.seconds, args.screenshot)
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    line = json.dumps(result)
    if args.json is not None:
        args.json.write_text(line + "\n")
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
