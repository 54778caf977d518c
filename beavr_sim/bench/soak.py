"""``python -m beavr_sim.bench soak --minutes N``: does a long mirrored session stay flat?

Plays a bundled trace in a loop (``teleop --repeat 0``) mirrored to the emulated rig (the
protocol emulators in a child process, driven through the vendors' SDKs), every run from a
synced rig as a recording day's episodes are, for ``--minutes`` of wall time, and samples
the resident memory (``VmRSS`` of ``/proc/<pid>/status``) of this process and of the emulator
process every ``--sample-s`` seconds. Reports the slope of a least-squares line through the
samples after the warm-up (MB per hour; its standard error), target <= 1 MB per hour for this
process: every per-write and per-frame statistic is kept in bounded form, so a day's session
holds what a minute's does. Beside the RSS it fits what the allocators hold in use: glibc's
``mallinfo2`` (:func:`beavr_sim.heap.in_use_mb`: numpy, MuJoCo, the SDKs) and
``sys.getallocatedblocks()`` (Python objects), so that a slope of the RSS alone (a buffer's
pages first written, allocator arenas) tells itself from a leak (in-use memory that grows).
It also fits the RSS's anonymous and file-backed parts (``RssAnon``, ``RssFile``: the heap and
stacks, the libraries' pages) and glibc's free bytes, and reports the thread count; ``--samples
FILE`` writes every sample. Sampling ends when the time is up, before the session is told to
stop: no sample is of the session closing (the rig, the recorder), only of it running.
JSON on the last stdout line. Figures: docs/hardware.md ("A recording day"),
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beavr_sim.heap import free_mb, in_use_mb
from beavr_sim.teleop.session import SessionOptions, run_session

#: The target slope of this process's resident memory after warm-up (MB per hour).
TARGET_MB_PER_HOUR = 1.0


def status_fields(pid: int | str = "self") -> dict[str, int]:
    """The numeric fields of ``/proc/<pid>/status`` (kB for memory, counts otherwise): VmRSS,
    RssAnon (heap, stacks: what a leak grows), RssFile (pages of mapped files: libraries' code
    first run), Threads; empty if the process is gone."""
    out: dict[str, int] = {}
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return out
    for line in text.splitlines():
        key, _, value = line.partition(":")
        parts = value.split()
        if parts and parts[0].isdigit():
            out[key] = int(parts[0])
    return out


def rss_mb(pid: int | str = "self") -> float | None:
    """Resident memory (MB) of a process from ``/proc/<pid>/status``; None if it is gone."""
    kb = status_fields(pid).get("VmRSS")
    return None if kb is None else kb / 1024.0


def child_pids(pid: int | str = "self") -> list[int]:
    """The direct children of a process (every thread's ``children`` file)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(p) for p in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return sorted(set(out))


@dataclass(frozen=True)
class Slope:
    """A least-squares line through (t, MB) samples: MB per hour and its standard error."""

    mb_per_hour: float | None
    stderr_mb_per_hour: float | None
    samples: int

    @classmethod
    def fit(cls, t_s: np.ndarray, mb: np.ndarray) -> Slope:
        t_s, mb = np.asarray(t_s, dtype=float), np.asarray(mb, dtype=float)
        if t_s.size < 3 or np.ptp(t_s) <= 0:
            return cls(None, None, int(t_s.size))
        hours = (t_s - t_s[0]) / 3600.0
        slope, intercept = np.polyfit(hours, mb, 1)
        dof = t_s.size - 2
        resid = mb - (slope * hours + intercept)
        sxx = float(np.sum((hours - hours.mean()) ** 2))
        err = float(np.sqrt(np.sum(resid**2) / dof / sxx)) if dof > 0 and sxx > 0 else None
        return cls(round(float(slope), 3), None if err is None else round(err, 3), int(t_s.size))


class RssSampler:
    """Samples this process's and its children's resident memory on a thread of its own."""

    def __init__(self, period_s: float):
        if not period_s > 0:
            raise ValueError(f"sample period must be positive, got {period_s}")
        self.period_s = float(period_s)
        self.t: list[float] = []
        self.own: list[float] = []
        self.children: list[float] = []
        #: What the allocators hold in use: malloc'd MB (nan where unknown), Python's blocks.
        self.malloc: list[float] = []
        self.malloc_free: list[float] = []
        self.py_blocks: list[int] = []
        #: The RSS split: anonymous (heap, stacks) and file-backed (libraries' pages) MB.
        self.anon: list[float] = []
        self.file: list[float] = []
        self.threads: list[int] = []
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            status = status_fields()
            kids = [rss_mb(pid) for pid in child_pids()]
            if "VmRSS" in status:
                self.t.append(time.monotonic() - self._t0)
                self.own.append(status["VmRSS"] / 1024.0)
                self.anon.append(status.get("RssAnon", 0) / 1024.0)
                self.file.append(status.get("RssFile", 0) / 1024.0)
                self.threads.append(status.get("Threads", 0))
                self.children.append(sum(k for k in kids if k is not None))
                in_use, free = in_use_mb(), free_mb()
                self.malloc.append(math.nan if in_use is None else in_use)
                self.malloc_free.append(math.nan if free is None else free)
                self.py_blocks.append(sys.getallocatedblocks())
            self._stop.wait(self.period_s)

    def columns(self) -> dict[str, list]:
        """Every sample, one list per quantity (for ``--samples FILE``)."""
        names = ("t", "own", "anon", "file", "threads", "children", "malloc", "malloc_free")
        out: dict[str, list] = {n: [None if v != v else v for v in getattr(self, n)] for n in names}
        out["py_blocks"] = list(self.py_blocks)
        return out

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


def run(
    minutes: float,
    task: str = "pour",
    embodiment: str | None = None,
    warmup_minutes: float | None = None,
    sample_s: float = 5.0,
    samples_path: Path | None = None,
) -> dict:
    """The soak (see the module docstring); warm-up default: a fifth of the run, at least a
    minute where the run is over two."""

    if not minutes > 0:
        raise ValueError(f"--minutes must be positive, got {minutes}")
    if warmup_minutes is None:
        warmup_minutes = max(0.2 * minutes, 1.0) if minutes > 2 else 0.2 * minutes
    if not 0 <= warmup_minutes < minutes:
        raise ValueError(f"warm-up ({warmup_minutes} min) must be shorter than the run")
    logging.basicConfig(level=logging.ERROR)
    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="trace",
        viser=False,
        headless=True,
        progress=False,
        repeat=0,
        mirror_hardware=True,
        hardware_config="emulated",
    )
    sampler = RssSampler(sample_s)
    sampler.start()
    t0 = time.monotonic()
    deadline = t0 + minutes * 60.0

    def time_is_up() -> bool:
        if time.monotonic() < deadline:
            return False
        sampler.stop()  # the last sample is of the session running, not closing
        return True

    try:
        summary = run_session(options, interrupted=time_is_up)
    finally:
        sampler.stop()
    wall_s = time.monotonic() - t0
    if samples_path is not None:
        samples_path.write_text(json.dumps(sampler.columns()))
    t = np.asarray(sampler.t)
    warm = t >= warmup_minutes * 60.0
    own = Slope.fit(t[warm], np.asarray(sampler.own)[warm])
    emulators = Slope.fit(t[warm], np.asarray(sampler.children)[warm])
    malloc_mb = np.asarray(sampler.malloc)
    known = warm & np.isfinite(malloc_mb)
    malloc = Slope.fit(t[known], malloc_mb[known])
    free_arr = np.asarray(sampler.malloc_free)
    free_known = warm & np.isfinite(free_arr)
    malloc_free = Slope.fit(t[free_known], free_arr[free_known])
    anon = Slope.fit(t[warm], np.asarray(sampler.anon)[warm])
    file_backed = Slope.fit(t[warm], np.asarray(sampler.file)[warm])
    threads = np.asarray(sampler.threads)[warm]
    blocks = Slope.fit(t[warm], np.asarray(sampler.py_blocks, dtype=float)[warm] / 1e3)
    return {
        "benchmark": "soak",
        "task": summary.task,
        "embodiment": summary.embodiment,
        "minutes": minutes,
        "wall_s": round(wall_s, 1),
        "warmup_minutes": round(warmup_minutes, 2),
        "runs": summary.runs,
        "successes": summary.successes,
        "hardware_faults": summary.hardware_faults,
        "failed_devices": summary.failed_devices,
        "ticks_late": summary.overruns,
        "rss_mb": {
            "start": round(sampler.own[0], 1) if sampler.own else None,
            "after_warmup": round(float(np.asarray(sampler.own)[warm][0]), 1)
            if warm.any()
            else None,
            "end": round(sampler.own[-1], 1) if sampler.own else None,
        },
        "rss_slope_mb_per_hour": own.mb_per_hour,
        "rss_slope_stderr_mb_per_hour": own.stderr_mb_per_hour,
        "samples_after_warmup": own.samples,
        "malloc_in_use_slope_mb_per_hour": malloc.mb_per_hour,
        "malloc_in_use_slope_stderr_mb_per_hour": malloc.stderr_mb_per_hour,
        "rss_anon_slope_mb_per_hour": anon.mb_per_hour,
        "rss_anon_slope_stderr_mb_per_hour": anon.stderr_mb_per_hour,
        "rss_file_slope_mb_per_hour": file_backed.mb_per_hour,
        "rss_file_slope_stderr_mb_per_hour": file_backed.stderr_mb_per_hour,
        "malloc_free_slope_mb_per_hour": malloc_free.mb_per_hour,
        "malloc_free_slope_stderr_mb_per_hour": malloc_free.stderr_mb_per_hour,
        "threads_after_warmup": [int(threads.min()), int(threads.max())] if threads.size else None,
        "python_blocks_slope_k_per_hour": blocks.mb_per_hour,
        "python_blocks_slope_stderr_k_per_hour": blocks.stderr_mb_per_hour,
        "emulator_rss_slope_mb_per_hour": emulators.mb_per_hour,
        "target_mb_per_hour": TARGET_MB_PER_HOUR,
        "within_target": own.mb_per_hour is not None and own.mb_per_hour <= TARGET_MB_PER_HOUR,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m beavr_sim.bench soak", description=__doc__)
    p.add_argument("--minutes", type=float, default=10.0, help="wall minutes (default 10)")
    p.add_argument("--task", default="pour", help="bundled trace's task (default pour)")
    p.add_argument("--embodiment", default=None, help="robot (default the trace's)")
    p.add_argument(
        "--warmup-minutes",
        type=float,
        default=None,
        help="left out of the fit (default a fifth of the run, at least 1 min over 2 min)",
    )
    p.add_argument("--sample-s", type=float, default=5.0, help="seconds between samples")
    p.add_argument("--samples", type=Path, default=None, help="write every sample (JSON) here")
    args = p.parse_args(argv)
    try:
        report = run(
            args.minutes,
            args.task,
            args.embodiment,
            args.warmup_minutes,
            args.sample_s,
            args.samples,
        )
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
