"""``python -m beavr_sim.bench contact``: contact settings compared on the grasping tasks.

For each contact setting (friction cone and impratio, :class:`ContactSettings`) and task, the
task's scripted expert runs ``episodes`` episodes (seeds 0 ..) on ``xarm7_leap_right`` and we
report:

- ``success``: successful episodes / episodes, and the failures' task details (first few);
- ``slip_mm_s``: how fast a held object moves in the hand: per control tick, for every task
  object whose centre is more than 2 cm above where it started (lifted: it can only be held),
  the change of its position in the frame of the hand body, over the tick (mm/s); p50 / p95
  over all such ticks. A perfect grip reads 0; the expert's own finger motion adds some;
- ``ms_per_step``: wall time of ``env.step`` (one control period of physics and the checker).

The experts were tuned on the default setting, which biases success towards it; the slip
figure does not depend on that.
"""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
from tqdm import tqdm

from beavr_sim.envs.registration import env_id
from beavr_sim.envs.scene import ContactSettings
from beavr_sim.experts.registry import expert_class

DEFAULT_TASKS = ("PickupBox", "PickPlace", "StackBlocks", "Pour")
DEFAULT_SETTINGS = (
    ContactSettings("pyramidal", 1.0),
    ContactSettings("elliptic", 10.0),
    ContactSettings("pyramidal", 10.0),
)
#: An object counts as lifted (held) this far above its starting height (m).
LIFTED_M = 0.02
EMBODIMENT = "xarm7_leap_right"


def parse_settings(text: str) -> tuple[ContactSettings, ...]:
    """``"pyramidal:1,elliptic:10"`` -> settings (cone:impratio, comma separated)."""
    out = []
    for item in text.split(","):
        cone, _, impratio = item.strip().partition(":")
        try:
            out.append(ContactSettings(cone, float(impratio or 1.0)))
        except ValueError as exc:
            raise ValueError(f"contact setting {item!r}: {exc}") from None
    return tuple(out)


def run_task(task: str, contact: ContactSettings, episodes: int, progress: bool = True) -> dict:
    env = gym.make(env_id(task), embodiment=EMBODIMENT, contact=contact).unwrapped
    try:
        expert = expert_class(task)(env)
        objects = [env.task.objects[name] for name in env.task.object_names]
        hand = env.model.body(f"{env.embodiment.effectors[0].name}/hand").id
        slips: list[float] = []
        failures: list[dict] = []
        successes, steps, wall = 0, 0, 0.0
        label = f"{contact.cone}:{contact.impratio:g} {task}"
        for seed in tqdm(range(episodes), desc=label, disable=not progress, leave=False):
            env.reset(seed=seed)
            expert.reset()
            start_z = [o.pos(env.data)[2] for o in objects]
            last: list[np.ndarray | None] = [None] * len(objects)
            done, info = False, {}
            while not done:
                action = expert.act()
                t0 = time.perf_counter()
                _, _, terminated, truncated, info = env.step(action)
                wall += time.perf_counter() - t0
                steps += 1
                done = terminated or truncated
                R_world_hand = env.data.xmat[hand].reshape(3, 3)
                for i, obj in enumerate(objects):
                    p = obj.pos(env.data)
                    if p[2] <= start_z[i] + LIFTED_M:
                        last[i] = None
                        continue
                    p_hand = R_world_hand.T @ (p - env.data.xpos[hand])
                    if last[i] is not None:
                        slips.append(float(np.linalg.norm(p_hand - last[i])) * env.control_hz)
                    last[i] = p_hand
            if info.get("is_success"):
                successes += 1
            elif len(failures) < 5:
                details = {k[5:]: v for k, v in info.items() if k.startswith("task/")}
                failures.append({"seed": seed, **details})
    finally:
        env.close()
    s = np.asarray(slips) * 1e3
    return {
        "success": f"{successes}/{episodes}",
        "success_rate": successes / episodes,
        "failures": failures,
        "slip_mm_s": {
            "p50": round(float(np.percentile(s, 50)), 2) if len(s) else None,
            "p95": round(float(np.percentile(s, 95)), 2) if len(s) else None,
            "held_ticks": len(s),
        },
        "ms_per_step": round(wall / max(steps, 1) * 1e3, 3),
    }


def run(
    settings: tuple[ContactSettings, ...] = DEFAULT_SETTINGS,
    tasks: tuple[str, ...] = DEFAULT_TASKS,
    episodes: int = 16,
    progress: bool = True,
) -> dict:
    """The benchmark's JSON-ready result: per setting (``cone:impratio``), per task."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    return {
        "embodiment": EMBODIMENT,
        "episodes": episodes,
        "settings": {
            f"{c.cone}:{c.impratio:g}": {t: run_task(t, c, episodes, progress) for t in tasks}
            for c in settings
        },
    }
