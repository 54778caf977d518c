"""``python -m beavr_sim.bench view``: what the browser view costs the teleop loop.

Replays the bundled Pour trace on the virtual clock as fast as the machine goes (the trace
starts over when it ends) for ``seconds`` of wall time, in these runs: without the view; with
the view as the session attaches it (updates at most 30 per wall second) and no browser; the
same with a client connected that reads every message (viser's WebSocket protocol, in this
process: the server's encoding and sending, without a browser's rendering); with headless
chromium showing the page (its software WebGL competes for the same cores; skipped without
chromium and playwright); and with a view updated every tick (no rate limit: what the limit
saves). The runs are interleaved over ``rounds`` rounds and the median kept. Reports each loop
rate (ticks per wall second), the ms per tick the runs with a view add to the run without
one, the view's own readout of its cost (:class:`~beavr_sim.viz.twin_view.ViewCost`: the
loop's time in the view and the server thread's CPU, per tick) and its updates per second.
"""

from __future__ import annotations

import os
import platform
import socket
import threading
import time
from contextlib import contextmanager

import numpy as np

from beavr_sim.assets import bundled_trace
from beavr_sim.bench.webxr import CHROMIUM_ARGS, find_chromium
from beavr_sim.headset.sources import TraceSource

TASK = "Pour"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def _websocket_client(url: str):
    """A client reading every message the view sends (viser's subprotocol), in a thread;
    entered once the first message came. (Not a browser: it sends no camera, so the view does
    not count it among its clients.)"""
    import viser
    from websockets.sync.client import connect

    stop, received = threading.Event(), threading.Event()
    ws = connect(
        url.replace("http://", "ws://"),
        max_size=None,
        subprotocols=[f"viser-v{viser.__version__}"],
    )

    def read() -> None:
        while not stop.is_set():
            try:
                ws.recv(timeout=0.2)
                received.set()
            except TimeoutError:
                continue
            except Exception:  # closed
                return

    reader = threading.Thread(target=read, name="bench-view-client", daemon=True)
    reader.start()
    try:
        if not received.wait(60.0):
            raise RuntimeError("the view sent nothing to a connected client in 60 s")
        yield
    finally:
        stop.set()
        reader.join(timeout=2.0)
        ws.close()


@contextmanager
def _chromium(url: str):
    """Headless chromium (software WebGL) showing the page until the scene is drawn."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=find_chromium(), headless=True, args=CHROMIUM_ARGS
        )
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            page.wait_for_selector("canvas", timeout=60_000)
            yield
        finally:
            browser.close()


def chromium_available() -> bool:

    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return False
    return find_chromium() is not None


@contextmanager
def _nothing():
    yield


def _wait_for_browser(view, timeout_s: float = 60.0) -> None:
    """Until a browser counts as connected (viser: once it sent its camera)."""
    deadline = time.monotonic() + timeout_s
    while view.clients < 1:
        if time.monotonic() > deadline:
            raise RuntimeError(f"no browser connected to the view in {timeout_s:g} s")
        time.sleep(0.05)


def _measure(
    seconds: float, view_rate_hz: float | None, client: str | None = None, clock: str = "virtual"
) -> dict:
    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        SessionOptions,
        build_loop,
    )
    from beavr_sim.teleop.view import attach_view  # local: heavy (the pipeline: mink, scipy)

    trace = bundled_trace(TASK)
    options = SessionOptions(
        task=TASK,
        source="trace",
        trace=trace,
        viser=view_rate_hz is not None,
        clock=clock,
        headless=True,
        progress=False,
    )
    loop = build_loop(options)
    view = None
    if view_rate_hz is not None:
        view = attach_view(loop, "127.0.0.1", _free_port(), rate_hz=view_rate_hz)
    clients = {None: None, "websocket": _websocket_client, "chromium": _chromium}
    try:
        connected = clients[client](view.url) if client else _nothing()
        with connected:
            if client == "chromium":
                _wait_for_browser(view)
            for _ in range(30):  # warm-up: first QP solves, caches
                loop.tick()
            updates_before = view.updates if view is not None else 0
            ticks, start = 0, time.perf_counter()
            while (elapsed := time.perf_counter() - start) < seconds:
                tick = loop.tick()
                ticks += 1
                if loop.source.finished or tick.state.terminated or tick.state.truncated:
                    loop.replace_source(TraceSource(trace, real_time=False))
                    loop.reset(loop.seed)
            out = {
                "ticks": ticks,
                "wall_s": round(elapsed, 3),
                "loop_rate_hz": ticks / elapsed,
                "missed_ticks": loop.schedule.missed_ticks,
            }
            if view is not None:
                out["view_updates"] = view.updates - updates_before
                busy, server = view.cost.per_second()
                rate = ticks / elapsed
                out["view_loop_ms_per_tick"] = 1e3 * busy / rate
                out["view_sending_ms_per_tick"] = None if server is None else 1e3 * server / rate
        return out
    finally:
        if view is not None:
            view.close()
        loop.source.close()
        loop.twin.env.close()


#: name -> (view updates per second at most: None without a view, 0 every tick; the client;
#: the clock: "virtual" as fast as possible, "paced" at the real 30 Hz control rate)
CONFIGS: dict[str, tuple[float | None, str | None, str]] = {
    "without_view": (None, None, "virtual"),
    "with_view_30hz": (30.0, None, "virtual"),
    "with_view_30hz_client": (30.0, "websocket", "virtual"),
    "with_view_30hz_chromium": (30.0, "chromium", "virtual"),
    "with_view_every_tick": (0.0, None, "virtual"),
    "paced_without_view": (None, None, "paced"),
    "paced_with_view_30hz_chromium": (30.0, "chromium", "paced"),
}


def _median(values) -> float | None:
    values = [v for v in values if v is not None]
    return round(float(np.median(values)), 3) if values else None


def run(seconds: float = 2.0, rounds: int = 3) -> dict:
    """``rounds`` rounds of the runs, interleaved (a busy machine's load drifts); each run
    ``seconds`` of wall time. Reports the median per configuration."""
    configs = {
        name: config
        for name, config in CONFIGS.items()
        if config[1] != "chromium" or chromium_available()
    }
    samples: dict[str, list[dict]] = {name: [] for name in configs}
    for _ in range(rounds):
        for name, (rate_hz, client, clock) in configs.items():
            samples[name].append(_measure(seconds, rate_hz, client, clock))
    out: dict = {
        "machine": f"{platform.machine()}, {platform.python_version()}, {os.cpu_count()} CPUs",
        "trace": bundled_trace(TASK).name,
        "clock": "virtual: as fast as possible; paced: the real 30 Hz rate",
        "seconds_per_run": seconds,
        "rounds": rounds,
    }
    bases = {
        clock: float(np.median([r["loop_rate_hz"] for r in samples[name]]))
        for clock, name in (("virtual", "without_view"), ("paced", "paced_without_view"))
    }
    for name, runs in samples.items():
        rates = [r["loop_rate_hz"] for r in runs]
        rate, base = float(np.median(rates)), bases[configs[name][2]]
        out[name] = {
            "loop_rate_hz": round(rate, 1),
            "loop_rate_hz_runs": [round(r, 1) for r in rates],
            "ratio": round(rate / base, 3),
        }
        if configs[name][2] == "virtual":
            out[name]["added_ms_per_tick"] = round(1e3 / rate - 1e3 / base, 3)
        else:
            out[name]["missed_ticks_per_s"] = _median(r["missed_ticks"] / r["wall_s"] for r in runs)
        if "view_updates" in runs[0]:
            out[name]["view_updates_per_s"] = round(
                float(np.median([r["view_updates"] / r["wall_s"] for r in runs])), 1
            )
            out[name]["readout_loop_ms_per_tick"] = _median(
                r["view_loop_ms_per_tick"] for r in runs
            )
            out[name]["readout_sending_ms_per_tick"] = _median(
                r["view_sending_ms_per_tick"] for r in runs
            )
    if len(configs) < len(CONFIGS):
        out["skipped"] = "the chromium runs: chromium or playwright not installed"
    return out
