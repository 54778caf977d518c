"""How much slower the same small piece of work runs after a gap than back to back.

A pipeline stage that handles one headset frame every 11 ms runs its code after an 11 ms gap,
every time. On a dedicated core that costs little: the caches and branch predictors still hold
the stage's code and data. On some virtual machines (this project's 2-core VM is one: a
Firecracker guest) they do not: the same work takes 10-20x as long after a gap of a few
milliseconds as it does back to back, whether the gap is spent sleeping or busy-waiting in
another piece of code. That bounds every per-frame latency from below, so the latency
benchmark reports this factor beside its figures: compare machines by it before comparing
their latencies.

``python -m beavr_sim.bench.machine [--gap-ms 11] [--repeats 200]``: JSON on the last line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np


def _python_work() -> int:
    return sum(range(200))


_A = np.linspace(0.0, 1.0, 64 * 64).reshape(64, 64)


def _numpy_work() -> float:
    return float((_A @ _A[:, 0]).sum())


WORKLOADS = {"python_sum_range_200": _python_work, "numpy_64x64_matvec": _numpy_work}


def _busy_wait(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def _median_us(work, gap_s: float, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        if gap_s > 0:
            _busy_wait(gap_s)
        t0 = time.perf_counter_ns()
        work()
        times.append((time.perf_counter_ns() - t0) / 1e3)
    return statistics.median(times)


def cold_factor(gap_ms: float = 11.0, repeats: int = 200) -> dict:
    """Median time of each workload back to back and after a ``gap_ms`` busy-wait; the ratio.

    A factor near 1 means per-frame code runs hot between frames; 10 or more means every stage
    of a pipeline pays its code's cold cost once per frame."""
    if not (gap_ms > 0 and repeats > 0):
        raise ValueError(f"gap_ms and repeats must be positive, got {gap_ms!r}, {repeats!r}")
    out: dict = {"gap_ms": gap_ms, "repeats": repeats, "workloads": {}}
    for name, work in WORKLOADS.items():
        for _ in range(50):  # warm up (first calls, allocations)
            work()
        hot = _median_us(work, 0.0, repeats)
        cold = _median_us(work, gap_ms / 1e3, repeats)
        out["workloads"][name] = {
            "hot_us": round(hot, 2),
            "after_gap_us": round(cold, 2),
            "factor": round(cold / hot, 1) if hot > 0 else None,
        }
    factors = [w["factor"] for w in out["workloads"].values() if w["factor"] is not None]
    out["factor"] = round(max(factors), 1) if factors else None
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m beavr_sim.bench.machine", description=__doc__)
    p.add_argument("--gap-ms", type=float, default=11.0, help="gap between runs (90 Hz: 11)")
    p.add_argument("--repeats", type=int, default=200, help="runs per median")
    args = p.parse_args(argv)
    try:
        result = cold_factor(args.gap_ms, args.repeats)
    except ValueError as err:
        p.error(str(err))
    for name, w in result["workloads"].items():
        print(
            f"{name:24s} back to back {w['hot_us']:8.2f} us   after {args.gap_ms:g} ms "
            f"{w['after_gap_us']:8.2f} us   x{w['factor']}",
            file=sys.stderr,
        )
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
