"""``python -m beavr_sim.bench teleop``: operator compute and in-process latency on VR traces.

Replays bundled traces (``assets/traces``) through the in-process pipeline on the virtual
clock and times, per control tick:

- operator compute per effector: ``observe`` of that side's new frames plus the effector's
  ``command`` (palm frame, filters, mapping, arm IK, LEAP retargeting). Target p99 <= 1 ms.
- motion-to-motion lag per effector (raw hand -> simulated hand, IK hand -> simulated hand, by
  cross-correlation; :mod:`beavr_sim.bench.tracking` defines them), next to the latencies;
- end-to-end latency: from the frame's delivery by the detector source to the command handed
  to the twin's actuators (``TeleopLoop`` measures it). Target p50 <= 1 ms.

Then it replays the first trace in real time at the control rate for ``seconds``
(``real_time``), the loop sleeping to its schedule as in a live session, and reports:

- control-loop jitter: ``|tick period - nominal period|`` with the period the time between
  the starts of consecutive ticks (the definition of ``python -m beavr_sim.eval --async``);
- real-time latency: frame received by the source (its poll) -> command applied, on the
  wall clock (it includes the operator compute, not the wait for the tick).

The first 10 ticks of every run (one-off work: first QPs, caches) are left out of all stats.
"""

from __future__ import annotations

import platform
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from beavr_sim.assets import bundled_trace
from beavr_sim.bench.timing import CallTimer
from beavr_sim.bench.tracking import StageRecorder, analyse, build_trace_loop
from beavr_sim.headset.sources import TraceSource

DEFAULT_TASKS = ("PickupBox", "Pour")
#: Ticks at the start of each run left out of the stats (first QPs, caches).
WARMUP_TICKS = 10


class EffectorCompute:
    """Per-tick operator compute of each effector: the time of its ``observe`` calls since its
    previous ``command`` plus that ``command`` (ms), one sample per command. Its
    :meth:`timer` times the effectors' own calls through the interpreter's monitoring
    (:class:`~beavr_sim.bench.timing.CallTimer`): nothing in the operator is replaced."""

    def __init__(self, effectors: Mapping):
        self._names = tuple(effectors)
        self._targets = {}
        for name, op in effectors.items():
            self._targets[f"{name}:observe"] = op.observe
            self._targets[f"{name}:command"] = op.command
        self._pending = dict.fromkeys(self._names, 0.0)
        #: Effector -> per-tick compute (ms).
        self.samples: dict[str, list[float]] = {name: [] for name in self._names}

    def timer(self) -> CallTimer:
        return CallTimer(self._targets, sink=self._add)

    def _add(self, label: str, seconds: float) -> None:
        name, _, call = label.rpartition(":")
        if call == "observe":
            self._pending[name] += seconds
        else:
            self.samples[name].append((self._pending[name] + seconds) * 1e3)
            self._pending[name] = 0.0


def _stats(ms) -> dict:
    a = np.asarray(ms)
    return {
        "p50": round(float(np.percentile(a, 50)), 4),
        "p99": round(float(np.percentile(a, 99)), 4),
        "mean": round(float(a.mean()), 4),
        "n": len(a),
    }


def run_real_time(path: Path, seconds: float) -> tuple[dict, dict]:
    """Replay ``path`` in real time at the control rate for ``seconds`` (the trace again
    from its start on a fresh episode if it ends first). Returns (stats, samples in ms)."""
    if not seconds > 0:
        raise ValueError(f"seconds must be positive, got {seconds}")
    _, loop = build_trace_loop(path, "real")
    dt = loop.dt
    # Per tick: its start (tick.t is time.monotonic() at the start of the tick in real time)
    # and the number of latencies measured so far (the listener runs after the tick).
    starts: list[float] = []
    counts: list[int] = []

    def listener(tick) -> None:
        starts.append(tick.t)
        counts.append(len(loop.latencies_ms))

    loop.listeners.append(listener)
    periods: list[float] = []
    latencies: list[float] = []
    played = 0.0
    try:
        while played < seconds - 1e-9:
            if played > 0:
                loop.replace_source(TraceSource(path, real_time=True))
            starts.clear()
            counts.clear()
            loop.latencies_ms.clear()
            loop.reset(loop.seed)  # the schedule starts now
            summary = loop.run(max_seconds=seconds - played, stop_on_success=False)
            played += summary.duration_s
            t = np.asarray(starts[WARMUP_TICKS:])
            periods += list(np.diff(t) * 1e3)
            # Latencies are per applied command; leave out those of the warm-up ticks.
            if len(counts) > WARMUP_TICKS:
                latencies += loop.latencies_ms[counts[WARMUP_TICKS - 1] :]
            if summary.ticks == 0:
                break
    finally:
        loop.twin.env.close()
    period_ms = dt * 1e3
    jitter = np.abs(np.asarray(periods) - period_ms)
    stats = {
        "trace": Path(path).name,
        "seconds": round(played, 3),
        "control_hz": round(1.0 / dt, 3),
        "period_ms": round(period_ms, 4),
        "control_jitter_ms": {
            "p50": round(float(np.percentile(jitter, 50)), 4) if jitter.size else None,
            "p99": round(float(np.percentile(jitter, 99)), 4) if jitter.size else None,
            "max": round(float(jitter.max()), 4) if jitter.size else None,
            "n": int(jitter.size),
        },
        "latency_ms": _stats(latencies) if latencies else {"n": 0},
    }
    return stats, {"control_jitter_ms": jitter, "latency_real_time_ms": np.asarray(latencies)}


def run(
    traces: list[Path] | None = None,
    *,
    real_time_seconds: float | None = 5.0,
    max_ticks: int | None = None,
    samples: dict | None = None,
) -> dict:
    """The benchmark's JSON-ready result.

    ``real_time_seconds``: length of the real-time replay (None: skip it). ``max_ticks``:
    stop each virtual-clock replay after this many control ticks (default: the whole trace;
    a short run for tests). ``samples``: a dict filled with the raw per-sample arrays (ms)
    that the histograms plot.
    """
    paths = traces or [bundled_trace(t) for t in DEFAULT_TASKS]
    per_trace = {}
    all_compute: list[float] = []
    all_latency: list[float] = []
    per_effector: dict[str, list[float]] = {}
    for path in paths:
        task, loop = build_trace_loop(path, "virtual")
        effectors = EffectorCompute(loop.operator.effectors)
        stages = StageRecorder(loop)  # after each tick, outside the timed calls
        loop.listeners.append(stages)
        with effectors.timer():
            summary = loop.run(max_seconds=None if max_ticks is None else max_ticks * loop.dt)
        loop.twin.env.close()
        compute = [s for t in effectors.samples.values() for s in t]
        # The first ticks include one-off work (first QP, caches): report them apart.
        steady = [s for t in effectors.samples.values() for s in t[WARMUP_TICKS:]]
        for name, t in effectors.samples.items():
            per_effector.setdefault(name, []).extend(t[WARMUP_TICKS:])
        all_compute += steady
        all_latency += loop.latencies_ms[WARMUP_TICKS:]
        per_trace[Path(path).name] = {
            "task": task,
            "success": summary.success,
            "ticks": summary.ticks,
            "operator_compute_ms_per_effector": _stats(steady),
            "first_tick_ms": round(compute[0], 3) if compute else None,
            "latency_ms": _stats(loop.latencies_ms[WARMUP_TICKS:]),
            "loop_rate_hz_virtual_clock": round(summary.loop_rate_hz or 0.0, 1),
            # Motion to motion (issue 26): raw hand -> IK hand -> simulated hand, per effector
            # (``bench tracking`` has the full breakdown and the definitions).
            "motion_lag_ms": {
                name: {**(b := analyse(a, loop.dt))["lag_wall_ms"], "tick": b["lag_ms"]}
                for name, a in stages.arrays().items()
                if len(a) > 2
            },
        }
    result = {
        "machine": f"{platform.machine()}, {platform.python_version()}",
        "operator_compute_ms_per_effector": _stats(all_compute),
        "target_operator_p99_ms": 1.0,
        "latency_in_process_ms": _stats(all_latency),
        "target_latency_p50_ms": 1.0,
        "traces": per_trace,
    }
    rt_samples: dict = {}
    if real_time_seconds is not None:
        result["real_time"], rt_samples = run_real_time(paths[0], real_time_seconds)
    if samples is not None:
        samples["operator_compute_ms_per_effector"] = {
            k: np.asarray(v) for k, v in per_effector.items()
        }
        samples["latency_in_process_ms"] = np.asarray(all_latency)
        samples.update(rt_samples)
    return result
