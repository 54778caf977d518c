"""Histograms of benchmark samples (PNG), like the BEAVR paper's latency and jitter figures.

``python -m beavr_sim.bench BENCH --plot DIR`` writes one figure per measured quantity into
``DIR``; the file names are stable (:data:`FILES`). Each figure shows the samples' histogram
(several series overlaid on shared bins when compared, e.g. ours against dex-retargeting),
their p50 and p99 as vertical lines with the values in the legend, the benchmark's target
when it has one, and the sample count. Counts go on a log scale when the tail is long (a few
samples far beyond the bulk would otherwise be invisible).

Matplotlib runs on its Agg backend: no display is needed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

#: File name of each plotted quantity -> what it shows (documented in docs/benchmarks.md).
FILES = {
    "teleop_operator_compute.png": "operator compute per control tick per effector (virtual clock)",
    "teleop_latency_in_process.png": "frame delivered -> command applied (virtual clock)",
    "teleop_latency_real_time.png": "frame received -> command applied (real-time replay)",
    "teleop_loop_jitter.png": "|tick period - nominal period| of the real-time control loop",
    "retarget_time.png": "LEAP retargeting time per frame, ours and dex-retargeting",
    "retarget_tip_error.png": "fingertip direction error per finger over the trace, both methods",
    "sim_env_step.png": "env.step time per embodiment (30 Hz control, no rendering)",
    "sim_render.png": "time per rendered 480x640 camera frame",
    "latency_send_to_twin.png": "latency harness: generator send -> command at the twin's actuators",
    "latency_send_to_driver.png": "latency harness: generator send -> emulated driver write",
}

#: ``latency --sweep --plot DIR``'s figures (one series per effector count).
LATENCY_SWEEP_FILES = {
    "latency_sweep_send_to_twin.png": "latency sweep: send -> twin's actuators per effector count",
    "latency_sweep_send_to_driver.png": "latency sweep: send -> emulated driver write per count",
}

_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown")


def percentiles(samples_ms: Sequence[float]) -> dict:
    """p50, p99, max and count of samples (ms), as the figures mark them."""
    a = np.asarray(samples_ms, dtype=float)
    if a.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
        "n": int(a.size),
    }


def long_tail(samples_ms: Sequence[float]) -> bool:
    """True when the top 5% of the samples spread over more of the axis than the other 95%
    (then linear counts would hide them next to the bulk)."""
    a = np.asarray(samples_ms, dtype=float)
    if a.size < 20:
        return False
    p95 = float(np.percentile(a, 95))
    return bool(a.max() - p95 > p95 - a.min())


def _fmt(ms: float) -> str:
    """3 significant digits, trailing zeros kept (0.0240, 1.20, 33.3, 152)."""
    return f"{f'{ms:#.3g}'.rstrip('.')} ms" if abs(ms) < 100 else f"{ms:.0f} ms"


def histogram(
    samples: Sequence[float] | Mapping[str, Sequence[float]],
    path: str | Path,
    *,
    title: str,
    xlabel: str,
    target: float | None = None,
    target_label: str | None = None,
    log_counts: bool | None = None,
    log_x: bool | None = None,
    bins: int = 60,
) -> dict:
    """Write a histogram of ``samples`` (ms) to ``path`` (PNG).

    ``samples`` is one array, or ``{label: array}`` for series overlaid on shared bins. Each
    series gets dashed p50 and dotted p99 lines in its colour, with the values in the legend;
    ``target`` (ms) draws a black line labelled ``target_label``. ``log_counts`` None: log
    scale when a series has a long tail (:func:`long_tail`). ``log_x`` None: log-spaced bins
    on a log time axis when compared series' medians differ more than 5x (all samples > 0).

    Returns ``{label: percentiles(...)}`` (label ``"samples"`` for a single array) plus the
    figure's ``"log_counts"`` and ``"log_x"``.
    """
    # A bare Figure (not pyplot) renders with Agg: no display, no global backend switch.
    from matplotlib.figure import Figure

    named = isinstance(samples, Mapping)  # series labelled in the legend
    series = (
        {str(k): np.asarray(v, dtype=float) for k, v in samples.items()}
        if named
        else {"samples": np.asarray(samples, dtype=float)}
    )
    series = {k: v[np.isfinite(v)] for k, v in series.items()}
    if not any(v.size for v in series.values()):
        raise ValueError(f"no samples to plot for {title!r}")
    stats = {k: percentiles(v) for k, v in series.items()}
    if log_counts is None:
        log_counts = any(long_tail(v) for v in series.values())
    everything = np.concatenate([v for v in series.values() if v.size])
    lo, hi = float(everything.min()), float(everything.max())
    if target is not None:
        lo, hi = min(lo, target), max(hi, target)
    medians = [v["p50"] for v in stats.values() if v["n"]]
    if log_x is None:
        log_x = lo > 0 and len(medians) > 1 and max(medians) > 5 * min(medians)
    log_x = bool(log_x and lo > 0)
    if hi - lo < 1e-9:
        lo, hi = (lo / 2, hi * 2) if log_x else (lo - 0.5, hi + 0.5)
    if log_x:
        edges = np.geomspace(lo, hi * 1.001, bins + 1)
    else:
        edges = np.linspace(lo, hi + 1e-3 * (hi - lo), bins + 1)

    several = len(series) > 1
    fig = Figure(figsize=(10.5 if several else 8, 4.5), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for i, (label, values) in enumerate(series.items()):
        color = _COLORS[i % len(_COLORS)]
        s = stats[label]
        name = f"{label}: " if named else ""
        if values.size:
            ax.hist(
                values,
                bins=edges,
                color=color,
                alpha=0.5 if several else 0.85,
                label=f"{label} (n = {s['n']}, max = {_fmt(s['max'])})" if named else None,
            )
            ax.axvline(
                s["p50"], color=color, ls="--", lw=1.6, label=f"{name}p50 = {_fmt(s['p50'])}"
            )
            ax.axvline(s["p99"], color=color, ls=":", lw=2.0, label=f"{name}p99 = {_fmt(s['p99'])}")
    if target is not None:
        ax.axvline(
            target, color="black", ls="-", lw=1.4, label=target_label or f"target {_fmt(target)}"
        )
    if log_counts:
        ax.set_yscale("log")
    if log_x:
        from matplotlib.ticker import FuncFormatter

        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
    ax.set_xlabel(xlabel + (" (log scale)" if log_x else ""))
    ax.set_ylabel("count (log scale)" if log_counts else "count")
    if named:
        ax.set_title(title, fontsize=11)
    else:
        s = stats["samples"]
        ax.set_title(f"{title}\nn = {s['n']}, max = {_fmt(s['max'])}", fontsize=11)
    ax.grid(alpha=0.3)
    if several:
        fig.legend(fontsize=9, loc="outside right upper")
    else:
        ax.legend(fontsize=9, loc="upper right")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return {**stats, "log_counts": bool(log_counts), "log_x": log_x}


# ---------------------------------------------------------------------------- per benchmark
def write_teleop(samples: Mapping[str, object], out: Path, result: Mapping | None = None) -> list:
    """The teleop benchmark's figures (see :data:`FILES`); the written paths."""
    result = result or {}
    op_target = result.get("target_operator_p99_ms")
    lat_target = result.get("target_latency_p50_ms")
    written = []

    def plot(name, data, **kwargs):
        if isinstance(data, Mapping):
            data = {k: v for k, v in data.items() if len(v)}
        if len(data):
            histogram(data, out / name, **kwargs)
            written.append(out / name)

    plot(
        "teleop_operator_compute.png",
        samples.get("operator_compute_ms_per_effector", {}),
        title="Operator compute per control tick, per effector (observe + command)",
        xlabel="compute time per tick (ms)",
        target=op_target,
        target_label=f"target p99 <= {op_target:g} ms" if op_target else None,
    )
    plot(
        "teleop_latency_in_process.png",
        samples.get("latency_in_process_ms", []),
        title="In-process latency, frame delivered -> command applied (virtual clock)",
        xlabel="latency (ms)",
        target=lat_target,
        target_label=f"target p50 <= {lat_target:g} ms" if lat_target else None,
    )
    plot(
        "teleop_latency_real_time.png",
        samples.get("latency_real_time_ms", []),
        title="Real-time latency, frame received -> command applied (trace at control rate)",
        xlabel="latency (ms)",
        target=lat_target,
        target_label=f"target p50 <= {lat_target:g} ms" if lat_target else None,
    )
    period = result.get("real_time", {}).get("period_ms")
    plot(
        "teleop_loop_jitter.png",
        samples.get("control_jitter_ms", []),
        title="Control-loop jitter, |tick period - nominal period|"
        + (f" (nominal {period:.4g} ms)" if period else ""),
        xlabel="period error (ms)",
    )
    return written


def write_retarget(samples: Mapping[str, object], out: Path, result: Mapping | None = None):
    """``samples``: ``time_ms`` (method -> ms per frame) and ``tip_error_deg`` (method ->
    frames x 4 fingers, in the order thumb, index, middle, ring)."""
    written = []
    series = {k: v for k, v in samples.get("time_ms", {}).items() if len(v)}
    if series:
        path = out / "retarget_time.png"
        histogram(
            series,
            path,
            title="LEAP retargeting time per frame (human hand trace)",
            xlabel="time per frame (ms)",
        )
        written.append(path)
    errors = {k: np.asarray(v, dtype=float) for k, v in samples.get("tip_error_deg", {}).items()}
    errors = {k: v for k, v in errors.items() if v.ndim == 2 and len(v)}
    if errors:
        path = out / "retarget_tip_error.png"
        tip_error_over_trace(errors, path)
        written.append(path)
    return written


def tip_error_over_trace(
    errors: Mapping[str, np.ndarray],
    path: Path,
    fingers: Sequence[str] = ("thumb", "index", "middle", "ring"),
) -> None:
    """One panel per finger: the direction error (deg) per frame, a line per method, the
    method's mean in the legend."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10.5, 2.1 * len(fingers) + 0.6), dpi=100, layout="constrained")
    axes = fig.subplots(len(fingers), 1, sharex=True)
    for f, ax in enumerate(np.atleast_1d(axes)):
        for i, (label, values) in enumerate(errors.items()):
            ax.plot(
                values[:, f],
                color=_COLORS[i % len(_COLORS)],
                lw=1.0,
                label=f"{label} (mean {values[:, f].mean():.2f} deg)",
            )
        ax.set_ylabel(f"{fingers[f]} (deg)")
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel("frame of the human hand trace")
    fig.suptitle("Fingertip direction error: human wrist -> tip against LEAP wrist -> pad")
    fig.savefig(path)


def write_sim(samples: Mapping[str, object], out: Path, result: Mapping | None = None):
    written = []
    steps = {k: v for k, v in samples.get("env_step_ms", {}).items() if len(v)}
    if steps:
        histogram(
            steps,
            out / "sim_env_step.png",
            title="env.step time per embodiment (one control step, no rendering)",
            xlabel="time per env.step (ms)",
        )
        written.append(out / "sim_env_step.png")
    if len(samples.get("render_ms", [])):
        histogram(
            samples["render_ms"],
            out / "sim_render.png",
            title="Time per rendered camera frame",
            xlabel="time per frame (ms)",
        )
        written.append(out / "sim_render.png")
    return written


def write_latency(samples: Mapping[str, object], out: str | Path, result: Mapping | None = None):
    """The latency harness's figures (one series per effector / device, and the floor); with
    ``--sweep``'s samples (``sweep_twin_ms_<n>``), one series per effector count instead."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if any(k.startswith("sweep_") for k in samples):
        return _write_latency_sweep(samples, out, result)
    config = f" (config {result['config']}, {result.get('layout', 'processes')})" if result else ""
    written = []
    for key, name, what in (
        ("latency_twin_ms_", "latency_send_to_twin.png", "command at the twin's actuators"),
        ("latency_driver_ms_", "latency_send_to_driver.png", "emulated driver write"),
    ):
        series = {
            k.removeprefix(key): v for k, v in samples.items() if k.startswith(key) and len(v)
        }
        title = f"Quest-protocol send -> {what}{config}"
        written += _latency_histogram(series, samples, out / name, title)
    return written


def _write_latency_sweep(samples: Mapping[str, object], out: Path, result: Mapping | None):
    hz = f", {result['headset_hz']:g} Hz" if result else ""
    written = []
    for kind, name, what in (
        ("twin", "latency_sweep_send_to_twin.png", "command at the twin's actuators"),
        ("driver", "latency_sweep_send_to_driver.png", "emulated driver write"),
    ):
        prefix = f"sweep_{kind}_ms_"
        counts = sorted(int(k.removeprefix(prefix)) for k in samples if k.startswith(prefix))
        series = {
            f"{n} effector{'s' if n > 1 else ''}": samples[f"{prefix}{n}"]
            for n in counts
            if len(samples[f"{prefix}{n}"])
        }
        title = f"Send -> {what} by effector count{hz} (concurrent, shared cores)"
        written += _latency_histogram(series, samples, out / name, title)
    return written


def _latency_histogram(series: dict, samples: Mapping, path: Path, title: str) -> list[Path]:
    """``series`` with the transport floor beside it, as ``path`` (nothing without data)."""
    if not series:
        return []
    if len(samples.get("floor_ms", [])):
        series["bare ZMQ hop (floor)"] = samples["floor_ms"]
    histogram(series, path, title=title, xlabel="latency (ms)")
    return [path]


WRITERS = {"teleop": write_teleop, "retarget": write_retarget, "sim": write_sim}


def write(benchmark: str, samples: Mapping, out: str | Path, result: Mapping | None = None):
    """Write ``benchmark``'s figures into ``out`` (created); the written paths as strings."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return [str(p) for p in WRITERS[benchmark](samples, out, result)]
