"""``python -m beavr_sim.bench teleop``: operator compute and in-process latency on VR traces.

Replays bundled traces (``assets/traces``) through the in-process pipeline on the virtual
clock and times, per control tick:

- operator compute per effector: ``observe`` of that side's new frames plus the effector's
  ``command`` (palm frame, filters, mapping, arm IK, LEAP retargeting). Target p99 <= 1 ms.
- end-to-end latency: from the frame's delivery by the detector source to the command handed
  to the twin's actuators (``TeleopLoop`` measures it). Target p50 <= 1 ms.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np

from beavr_sim.assets import bundled_trace

DEFAULT_TASKS = ("PickupBox", "Pour")


class _TimedEffector:
    """Wraps an EffectorOperator's observe/command with per-tick timers."""

    def __init__(self, op):
        self.op = op
        self.tick_s = 0.0
        self.samples: list[float] = []
        self._observe, self._command = op.observe, op.command
        op.observe = self.observe
        op.command = self.command

    def observe(self, frame):
        t0 = time.perf_counter()
        try:
            return self._observe(frame)
        finally:
            self.tick_s += time.perf_counter() - t0

    def command(self, now, paused):
        t0 = time.perf_counter()
        try:
            return self._command(now, paused)
        finally:
            self.samples.append((self.tick_s + time.perf_counter() - t0) * 1e3)
            self.tick_s = 0.0


def _stats(ms) -> dict:
    a = np.asarray(ms)
    return {
        "p50": round(float(np.percentile(a, 50)), 4),
        "p99": round(float(np.percentile(a, 99)), 4),
        "mean": round(float(a.mean()), 4),
        "n": len(a),
    }


def run(traces: list[Path] | None = None) -> dict:
    from beavr_sim.teleop.session import SessionOptions, build_loop

    paths = traces or [bundled_trace(t) for t in DEFAULT_TASKS]
    per_trace = {}
    all_compute: list[float] = []
    all_latency: list[float] = []
    for path in paths:
        from beavr_sim.traces.format import TraceReader

        task = TraceReader(path).metadata.task
        options = SessionOptions(
            task=task, source="trace", trace=Path(path), viser=False, headless=True, progress=False
        )
        loop = build_loop(options)
        timers = {name: _TimedEffector(op) for name, op in loop.operator.effectors.items()}
        summary = loop.run()
        loop.twin.env.close()
        compute = [s for t in timers.values() for s in t.samples]
        # The first ticks include one-off work (first QP, caches): report them apart.
        steady = [s for t in timers.values() for s in t.samples[10:]]
        all_compute += steady
        all_latency += loop.latencies_ms[10:]
        per_trace[Path(path).name] = {
            "task": task,
            "success": summary.success,
            "ticks": summary.ticks,
            "operator_compute_ms_per_effector": _stats(steady),
            "first_tick_ms": round(compute[0], 3) if compute else None,
            "latency_ms": _stats(loop.latencies_ms[10:]),
            "loop_rate_hz_virtual_clock": round(summary.loop_rate_hz or 0.0, 1),
        }
    return {
        "machine": f"{platform.machine()}, {platform.python_version()}",
        "operator_compute_ms_per_effector": _stats(all_compute),
        "target_operator_p99_ms": 1.0,
        "latency_in_process_ms": _stats(all_latency),
        "target_latency_p50_ms": 1.0,
        "traces": per_trace,
    }
