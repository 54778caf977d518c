"""``python -m beavr_sim.bench hardware``: hardware mirroring on emulated devices.

Replays a bundled trace (default pour) at the real control rate (the paced virtual clock, as
``teleop --mirror-hardware`` does for traces) on the emulated
rig (an xArm7 controller emulator and a Dynamixel bus emulator in a child process, driven by
the real ``xarm-python-sdk`` and ``dynamixel-sdk``) and reports, per device:

- write rate: control ticks whose target was written, per second, and as a share of the
  control rate (target >= 99.8 %);
- write latency: from the guarded command handed to the mirror (the twin's tick) to the first
  bytes of its write having left the driver (the SDK call returned), p50 / p99;
- divergence: the largest |measured - twin| joint gap over the run (the emulated fingers close
  on nothing, so the hand's is the grasp's depth into the object);

and the guard's cost per tick (all rules, path included) on the twin's thread. The emulators
are not hardware: the bus and controller timings of a real rig differ (docs/hardware.md).
"""

from __future__ import annotations

import numpy as np

from beavr_sim.bench.timing import CallTimer

DEFAULT_TASK = "Pour"


def _stats(values) -> dict:
    a = np.asarray(values, dtype=float)
    if not a.size:
        return {"p50": None, "p99": None, "n": 0}
    return {
        "p50": round(float(np.percentile(a, 50)), 4),
        "p99": round(float(np.percentile(a, 99)), 4),
        "max": round(float(a.max()), 4),
        "n": int(a.size),
    }


def run(task: str = DEFAULT_TASK, samples: dict | None = None) -> dict:
    from beavr_sim.hardware.mirror import HardwareMirror  # local: heavy (the pipeline: mink, scipy)
    from beavr_sim.hardware.rig import EmulatedRig  # local: heavy (mujoco)
    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        SessionOptions,
        build_loop,
    )

    options = SessionOptions(
        task=task, source="trace", viser=False, headless=True, progress=False, clock="paced"
    )
    loop = build_loop(options)
    env = loop.twin.env
    rig = EmulatedRig(env.embodiment, env.joints)
    mirror = HardwareMirror(rig.config, env.embodiment, env.joints, env.model, env.control_hz)
    guard_ms: list[float] = []
    # The twin's guard's checks (not the mirror's guard), timed by the interpreter's monitoring.
    guard_timer = CallTimer(
        {"guard": loop.twin.guard.filter}, sink=lambda _, s: guard_ms.append(s * 1e3)
    )
    try:
        q = mirror.connect()
        loop.reset(loop.seed, robot_qpos=q)
        mirror.start(loop.twin.action)
        loop.listeners.insert(
            0,
            lambda tick: mirror.submit(
                tick.state.action, tick.state.positions, tick.state.guard_blocked_effectors
            ),
        )
        with guard_timer:
            summary = loop.run()
    finally:
        mirror.close()
        rig.close()
        env.close()
    devices = {}
    for link in mirror.links:
        s = link.stats
        times = np.asarray(s.write_times)
        span = times[-1] - times[0] if times.size > 1 else float("nan")
        rate = (times.size - 1) / span if times.size > 1 else None
        devices[link.name] = {
            "writes": int(times.size),
            "ticks": summary.ticks,
            "write_rate_hz": round(rate, 2) if rate else None,
            "write_rate_pct_of_control": round(100 * rate / env.control_hz, 2) if rate else None,
            "ticks_written_pct": round(100 * times.size / max(1, summary.ticks), 2),
            "write_latency_ms": _stats(s.write_latency_ms),
            "max_divergence_rad": round(s.max_divergence_rad, 4),
            "max_divergence_joint": s.max_divergence_joint,
            "targets_sent": s.commands_sent,
            "errors": s.errors,
            "holds": s.holds,
        }
        if samples is not None:
            samples[f"write_latency_ms_{link.name}"] = list(s.write_latency_ms)
    if samples is not None:
        samples["guard_ms"] = guard_ms
    return {
        "task": summary.task,
        "success": summary.success,
        "control_hz": env.control_hz,
        "ticks": summary.ticks,
        "loop_rate_hz": round(summary.loop_rate_hz, 2) if summary.loop_rate_hz else None,
        "guard_ms_per_tick": _stats(guard_ms[10:]),
        "devices": devices,
        "note": "emulated devices (child process), real SDKs; not a real rig",
    }
