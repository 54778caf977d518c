"""``python -m beavr_sim.bench view``: what the browser view costs the teleop loop.

Replays the bundled Pour trace on the virtual clock as fast as the machine goes (the trace
starts over when it ends) for ``seconds`` of wall time, three times: without the view, with
the view as the session attaches it (updates at most 30 per wall second), and with a view
updated every tick (no rate limit: what the limit saves); the three are interleaved over
``rounds`` rounds and the median kept. Reports each loop rate (ticks per wall second), the
view's updates per second, and the ratios to the run without the view. No browser is
connected: the server still builds and queues every message.
"""

from __future__ import annotations

import os
import platform
import socket
import time

import numpy as np

from beavr_sim.assets import bundled_trace
from beavr_sim.headset.sources import TraceSource

TASK = "Pour"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _measure(seconds: float, view_rate_hz: float | None) -> dict:
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
        clock="virtual",
        headless=True,
        progress=False,
    )
    loop = build_loop(options)
    view = None
    if view_rate_hz is not None:
        view = attach_view(loop, "127.0.0.1", _free_port(), rate_hz=view_rate_hz)
    try:
        for _ in range(30):  # warm-up: first QP solves, caches
            loop.tick()
        if view is not None:
            view.updates = 0
        ticks, start = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - start) < seconds:
            tick = loop.tick()
            ticks += 1
            if loop.source.finished or tick.state.terminated or tick.state.truncated:
                loop.replace_source(TraceSource(trace, real_time=False))
                loop.reset(loop.seed)
        out = {"ticks": ticks, "wall_s": round(elapsed, 3), "loop_rate_hz": ticks / elapsed}
        if view is not None:
            out["view_updates"] = view.updates
        return out
    finally:
        if view is not None:
            view.close()
        loop.source.close()
        loop.twin.env.close()


CONFIGS = {"without_view": None, "with_view_30hz": 30.0, "with_view_every_tick": 0.0}


def run(seconds: float = 2.0, rounds: int = 3) -> dict:
    """``rounds`` rounds of the three runs, interleaved (a busy machine's load drifts); each
    run ``seconds`` of wall time. Reports the median rate per configuration."""
    samples: dict[str, list[dict]] = {name: [] for name in CONFIGS}
    for _ in range(rounds):
        for name, rate_hz in CONFIGS.items():
            samples[name].append(_measure(seconds, rate_hz))
    out: dict = {
        "machine": f"{platform.machine()}, {platform.python_version()}, {os.cpu_count()} CPUs",
        "trace": bundled_trace(TASK).name,
        "clock": "virtual, as fast as possible",
        "seconds_per_run": seconds,
        "rounds": rounds,
    }
    for name, runs in samples.items():
        rates = [r["loop_rate_hz"] for r in runs]
        out[name] = {
            "loop_rate_hz": round(float(np.median(rates)), 1),
            "loop_rate_hz_runs": [round(r, 1) for r in rates],
        }
        if "view_updates" in runs[0]:
            out[name]["view_updates_per_s"] = round(
                float(np.median([r["view_updates"] / r["wall_s"] for r in runs])), 1
            )
    base = out["without_view"]["loop_rate_hz"]
    out["ratio_with_view_30hz"] = round(out["with_view_30hz"]["loop_rate_hz"] / base, 3)
    out["ratio_with_view_every_tick"] = round(out["with_view_every_tick"]["loop_rate_hz"] / base, 3)
    return out
