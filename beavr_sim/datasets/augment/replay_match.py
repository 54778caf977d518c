"""Seeds of a source without environment state, found by replaying its actions.

The twin is deterministic and the robot starts every reset at the same joints, so an episode
recorded at seed ``s`` is reproduced exactly when its recorded actions are stepped from the
task's reset at ``s``: the measured joints (``observation.state``, the observation before each
action) come back frame by frame. At another seed they agree until the hand reaches where the
objects stand: the object is elsewhere, the fingers close on something else or on nothing, and
the joints part. So candidate seeds are tried in order (:attr:`MatchConfig.seeds`) and the
first whose replay reproduces every recorded frame within :attr:`MatchConfig.tolerance`, and
in which the robot touched an object (otherwise any seed that leaves the hand's path clear
would reproduce it), is the episode's.

Cheap first: a candidate whose objects' bounding spheres, at their reset, never overlap the
robot's geoms' (placed by forward kinematics of the recorded joints) at any frame cannot be
the one (the first touch of an object happens where the reset put it); it is skipped without
replaying. A replay stops at the first frame that parts (a wrong seed costs the frames up to
its grasp, about 0.2 s for a PickPlace episode).

Where it fails: a seed outside the candidates; an episode in which the robot touched nothing
(no frame tells the seeds apart); joints that the twin did not produce (a mirrored real rig's
measured ``observation.state``, a recording that started after the reset, a twin of another
MuJoCo build). Those are refused: record the source with ``--environment-state`` or keep its
``meta/beavr_episodes.jsonl``.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from beavr_sim.tasks.checks import in_contact


@dataclass(frozen=True)
class MatchConfig:
    seeds: range = range(10_000)  # candidate seeds, tried in order
    tolerance: float = 1e-3  # rad (or m): largest joint difference of a reproduced frame
    margin: float = 0.01  # m: added to the bounding spheres of the cheap test


@dataclass(frozen=True)
class Recorded:
    """One recorded episode: its actions and the joints measured before each."""

    actions: np.ndarray  # (frames, joints)
    states: np.ndarray  # (frames, joints): observation.state


def _swept(env, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres and bounding radii of the robot's geoms at every recorded frame."""
    model, data = env.model, env.data
    geoms = np.asarray(env.task.robot_geoms, int)
    centres = np.zeros((len(states), len(geoms), 3))
    for k, q in enumerate(states):
        data.qpos[env.joints.qpos_adr] = q
        mujoco.mj_kinematics(model, data)
        centres[k] = data.geom_xpos[geoms]
    radii = np.tile(model.geom_rbound[geoms], len(states))
    return centres.reshape(-1, 3), radii


def _within_reach(env, swept: tuple[np.ndarray, np.ndarray], margin: float) -> bool:
    """Whether some object geom, where the reset put it, overlaps a robot geom at some frame."""
    centres, radii = swept
    for obj in env.task.objects.values():
        for g in obj.geom_ids:
            gap = np.linalg.norm(centres - env.data.geom_xpos[g], axis=1) - radii
            if (gap < env.model.geom_rbound[g] + margin).any():
                return True
    return False


def _reproduces(env, episode: Recorded, tolerance: float) -> str:
    """``"yes"`` when stepping ``episode``'s actions from the env's current reset gives back
    its recorded joints with the robot touching an object on the way, ``"untouched"`` when it
    gives them back touching nothing, ``"no"`` when they part."""
    model, data = env.model, env.data
    objects = [g for o in env.task.objects.values() for g in o.geom_ids]
    robot = env.task.robot_geoms
    if np.abs(env.agent_pos - episode.states[0]).max() > tolerance:
        return "no"
    touched = False
    for k, action in enumerate(episode.actions[:-1]):
        env.advance(action)
        if np.abs(env.agent_pos - episode.states[k + 1]).max() > tolerance:
            return "no"
        touched = touched or in_contact(model, data, objects, robot)
    return "yes" if touched else "untouched"


def match_seeds(
    env, episodes: dict[int, Recorded], config: MatchConfig | None = None
) -> tuple[dict[int, int], dict[int, str]]:
    """Episode index -> the first candidate seed whose replay reproduces it (see the module
    docstring), and for each episode none reproduced, why (one line)."""
    config = config or MatchConfig()
    swept = {e: _swept(env, ep.states) for e, ep in episodes.items()}
    found: dict[int, int] = {}
    untouched: set[int] = set()
    for seed in config.seeds:
        if len(found) == len(episodes):
            break
        env.reset(seed=seed)
        for e, episode in episodes.items():
            if e in found or not _within_reach(env, swept[e], config.margin):
                continue
            verdict = _reproduces(env, episode, config.tolerance)
            if verdict == "yes":
                found[e] = seed
            elif verdict == "untouched":
                untouched.add(e)
            env.reset(seed=seed)
    first, last = config.seeds.start, config.seeds.stop - 1
    why = {
        e: "the robot touches no object in it: its joints do not tell the seeds apart"
        if e in untouched
        else f"no reset at seeds {first}..{last} reproduces its observation.state when its "
        "actions are replayed"
        for e in episodes
        if e not in found
    }
    return found, why
