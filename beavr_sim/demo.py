"""``python -m beavr_sim.demo``: the twin on a scripted motion, watched in the browser.

Until the teleop pipeline lands this is what ``make demo`` runs: the Playground env at its
control rate, the arm(s) sweeping around home while the hand(s) open and close.
"""

from __future__ import annotations

import argparse
import sys
import time

import gymnasium as gym
import numpy as np

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.robots import EMBODIMENTS
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT, embodiment_spec
from beavr_sim.robots.identity import embodiment_label
from beavr_sim.viz.twin_view import TwinView


def scripted_targets(env, t: float) -> np.ndarray:
    """Joint targets at time ``t``: arm sway around home, a slow grasp cycle."""
    u = env.unwrapped
    target = u.joints.home.copy()
    grasp = 0.5 * (1 - np.cos(2 * np.pi * t / 4.0))  # 0 open .. 1 closed, 4 s period
    for eff in u.embodiment.effectors:
        sl = u.joints.slices[eff.name]
        arm = target[sl][:7]
        arm[0] += 0.35 * np.sin(2 * np.pi * t / 8.0)
        arm[3] += 0.25 * np.sin(2 * np.pi * t / 6.0)
        arm[5] += 0.2 * np.sin(2 * np.pi * t / 5.0)
        hand = target[sl][7:]
        hand[[1, 5, 9]] = 1.2 * grasp  # MCP flexion, index/middle/ring
        hand[[2, 6, 10]] = 0.9 * grasp
        hand[[3, 7, 11]] = 0.6 * grasp
        hand[[12, 13]] = (1.4 * grasp, 0.6 * grasp)
        target[sl] = np.r_[arm, hand]
    return np.clip(target, u.joints.lower, u.joints.upper).astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.demo", description=__doc__)
    parser.add_argument(
        "--embodiment",
        default=DEFAULT_EMBODIMENT,
        help=f"{', '.join(sorted(EMBODIMENTS))}, or a robot file (path/to/robot.toml)",
    )
    parser.add_argument(
        "--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)"
    )
    parser.add_argument("--no-viser", action="store_true", help="no browser view")
    parser.add_argument("--viser-host", default="127.0.0.1")
    parser.add_argument("--viser-port", type=int, default=8080)
    args = parser.parse_args(argv)
    try:
        label = embodiment_label(embodiment_spec(args.embodiment).name)
    except (ValueError, OSError) as exc:  # unknown name, missing or unreadable robot file
        parser.error(str(exc))

    env = gym.make("beavr_sim/Playground-v0", embodiment=args.embodiment, max_episode_seconds=1e9)
    env.reset(seed=0)
    u = env.unwrapped
    view = None
    if not args.no_viser:
        view = TwinView(
            u.render_model,
            host=args.viser_host,
            port=args.viser_port,
            title=f"beavr_sim — Playground — {label}",
        )
        print(f"browser view: {view.url}", flush=True)
    period = 1.0 / u.control_hz
    t_sim, next_tick, last_print = 0.0, time.perf_counter(), time.perf_counter()
    ticks = 0
    try:
        while args.seconds <= 0 or t_sim < args.seconds:
            if view is not None and view.take_reset():
                env.reset(seed=0)
                t_sim = 0.0
            if view is None or not view.paused:
                env.step(scripted_targets(env, t_sim))
                t_sim += period
                ticks += 1
            if view is not None:
                view.update(u.data, status=f"**Playground** · {label} · t = {t_sim:5.1f} s")
            now = time.perf_counter()
            if now - last_print >= 1.0:
                print(f"\rt={t_sim:6.1f} s  ticks={ticks}", end="", file=sys.stderr, flush=True)
                last_print = now
            next_tick += period
            time.sleep(max(0.0, next_tick - time.perf_counter()))
    except KeyboardInterrupt:
        pass
    finally:
        print(file=sys.stderr)
        if view is not None:
            view.close()
        env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
