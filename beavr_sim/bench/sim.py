"""Simulation speed: physics steps/s and env steps/s per embodiment, ms per rendered frame."""

from __future__ import annotations

import platform
import time
from collections.abc import Callable

import gymnasium as gym
import mujoco
import numpy as np

from beavr_sim.reference import build_reference_model, find_reference_dir
from beavr_sim.robots import EMBODIMENTS


def _rate(
    fn: Callable[[], None], batch: int, seconds: float, times_ms: list | None = None
) -> float:
    """Calls of ``fn`` per second (``batch`` units per call), measured for ~``seconds``;
    ``times_ms`` gets each call's duration (ms) when given."""
    fn()  # warm up
    count, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        if times_ms is None:
            fn()
        else:
            t0 = time.perf_counter()
            fn()
            times_ms.append((time.perf_counter() - t0) * 1e3)
        count += batch
    return count / elapsed


def _physics_rate(model: mujoco.MjModel, data: mujoco.MjData, seconds: float) -> float:
    """Physics steps/s with the robot tracking a slow sinusoid around its start pose."""
    q0 = data.ctrl.copy()
    phase = np.linspace(0, np.pi, model.nu)
    t = [0.0]

    def block():
        t[0] += 0.05
        data.ctrl[:] = q0 + 0.05 * np.sin(t[0] + phase)
        mujoco.mj_step(model, data, nstep=100)

    return _rate(block, 100, seconds)


def run(
    seconds: float = 2.0,
    render_frames: int = 20,
    height: int = 480,
    width: int = 640,
    samples: dict | None = None,
) -> dict:
    """The JSON-ready result. ``samples``: a dict filled with per-call times (ms):
    ``env_step_ms`` ({embodiment: array}) and ``render_ms``."""
    samples = {} if samples is None else samples
    step_ms: dict[str, list[float]] = samples.setdefault("env_step_ms", {})
    result: dict = {
        "machine": {
            "python": platform.python_version(),
            "mujoco": mujoco.__version__,
            "processor": platform.processor() or platform.machine(),
        },
        "seconds_per_measurement": seconds,
        "embodiments": {},
    }
    for name in EMBODIMENTS:
        env = gym.make("beavr_sim/Playground-v0", embodiment=name)
        env.reset(seed=0)
        u = env.unwrapped
        physics = _physics_rate(u.model, u.data, seconds)
        obs, _ = env.reset(seed=0)
        env.action_space.seed(0)
        home = obs["agent_pos"]
        rng = np.random.default_rng(0)

        def env_step(env=env, home=home, rng=rng):
            env.step(home + rng.normal(0, 0.02, home.shape).astype(np.float32))

        env_rate = _rate(env_step, 1, seconds, step_ms.setdefault(name, []))
        result["embodiments"][name] = {
            "physics_steps_per_s": round(physics),
            "env_steps_per_s": round(env_rate),
            "control_hz": u.control_hz,
            "physics_dt_s": u.model.opt.timestep,
            "physics_steps_per_env_step": u.n_substeps,
            "ngeom": u.model.ngeom,
        }
        env.close()

    env = gym.make(
        "beavr_sim/Playground-v0", render_mode="rgb_array", camera_height=height, camera_width=width
    )
    env.reset(seed=0)
    u = env.unwrapped
    u.render_camera("front")  # create the GL context outside the timing
    render_ms: list[float] = []
    start = time.perf_counter()
    for i in range(render_frames):
        t0 = time.perf_counter()
        u.render_camera("front" if i % 2 == 0 else "overhead")
        render_ms.append((time.perf_counter() - t0) * 1e3)
    result["render_ms_per_frame"] = round(1000 * (time.perf_counter() - start) / render_frames, 2)
    samples["render_ms"] = render_ms
    result["render_size"] = [height, width]
    env.close()

    reference_dir = find_reference_dir()
    if reference_dir is None:
        result["reference"] = "skipped: ../shared/reference not found"
    else:
        single = gym.make("beavr_sim/Playground-v0").unwrapped
        ref = build_reference_model(
            single.embodiment, single.model, reference_dir, keep_meshes=True
        )
        ref.opt.timestep = single.model.opt.timestep
        ref_data = mujoco.MjData(ref)
        mujoco.mj_forward(ref, ref_data)
        result["reference"] = {
            "model": "Menagerie xArm7 + LEAP right (mesh collision), same mount and timestep",
            "physics_steps_per_s": round(_physics_rate(ref, ref_data, seconds)),
        }
    return result
