"""A way around for a mirrored catch-up whose straight joint-space path the guard refuses.

:func:`plan_detour` returns waypoints (action order) from ``start`` to ``goal`` such that every
leg, a straight joint-space segment, passes a :class:`~beavr_sim.twin.guard.CollisionGuard`
(geometric rules sampled along the leg: joint limits, workspace, contacts with the scene, the
episode's fixtures and the other links). It tries, cheapest first:

1. the straight segment;
2. the joint groups (each effector's arm and its hand) moved one group at a time, in every
   order (e.g. the arms to the start pose with the hands as they are, then the hands);
3. a seeded RRT-connect in joint space between ``start`` and ``goal``, its path shortcut.

Contract: deterministic (``seed``), bounded (``max_checks`` guard checks, ``budget_s`` of
wall time), never raises on a planning failure: it returns a :class:`Detour` whose ``reason``
says in one line why no path was found. It plans only; the caller sends the legs at its own
speed cap and checks every target it sends again.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from beavr_sim.twin.guard import CollisionGuard


@dataclass(frozen=True)
class DetourConfig:
    """Bounds of one planning attempt."""

    #: Guard checks (each samples a whole leg) one attempt may spend.
    max_checks: int = 4000
    #: Wall seconds one attempt may spend.
    budget_s: float = 2.0
    #: Largest joint-space step (rad, max over joints) the RRT extends a tree by.
    rrt_step: float = 0.25
    #: Probability that an RRT sample is the other tree's newest node.
    goal_bias: float = 0.2
    #: Shortcut attempts on the RRT's path.
    shortcuts: int = 60
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_checks < 1 or not self.budget_s > 0 or not self.rrt_step > 0:
            raise ValueError(
                "DetourConfig: max_checks, budget_s and rrt_step must be positive, got "
                f"{self.max_checks}, {self.budget_s}, {self.rrt_step}"
            )
        if not 0 <= self.goal_bias <= 1:
            raise ValueError(f"DetourConfig.goal_bias must be in [0, 1], got {self.goal_bias}")


@dataclass(frozen=True)
class Detour:
    """Waypoints after ``start`` (the last is the goal), or none and why."""

    waypoints: tuple[np.ndarray, ...]
    #: How it was found: "straight", "groups", "rrt"; "" when not found.
    method: str
    checks: int
    reason: str = ""

    @property
    def found(self) -> bool:
        return bool(self.waypoints)


class _OutOfBudget(Exception):
    pass


def joint_groups(guard: CollisionGuard) -> list[np.ndarray]:
    """Action indices per group: each effector's arm joints, then its hand joints (a group
    left out when empty), then the joints of no effector."""
    groups = []
    rest = np.ones(guard.joints.size, dtype=bool)
    for sl in sorted(guard.slices.values(), key=lambda sl: sl.start):
        idx = np.arange(guard.joints.size)[sl]
        rest[idx] = False
        for part in (idx[~guard.hand_joints[idx]], idx[guard.hand_joints[idx]]):
            if part.size:
                groups.append(part)
    if rest.any():  # joints of no effector (a humanoid's body): one group
        groups.append(np.flatnonzero(rest))
    return groups


def plan_detour(
    guard: CollisionGuard,
    start: np.ndarray,
    goal: np.ndarray,
    qpos_now: np.ndarray,
    config: DetourConfig = DetourConfig(),
    clock: Callable[[], float] = time.monotonic,
) -> Detour:
    """Waypoints from ``start`` to ``goal`` whose legs ``guard`` accepts (module docstring).

    ``guard`` is checked without velocity rules (its ``dt`` is ignored: only configurations
    and paths); objects stand as in ``qpos_now``."""
    start = np.asarray(start, dtype=np.float64)
    goal = np.asarray(goal, dtype=np.float64)
    checks = 0
    deadline = clock() + config.budget_s

    def leg_ok(a: np.ndarray, b: np.ndarray) -> bool:
        nonlocal checks
        if checks >= config.max_checks or clock() > deadline:
            raise _OutOfBudget
        checks += 1
        saved, guard.dt = guard.dt, None  # geometry and limits only: the caller paces legs
        try:
            return guard.check(b, qpos_now, a).ok
        finally:
            guard.dt = saved

    try:
        if leg_ok(start, goal):
            return Detour((goal.copy(),), "straight", checks)
        path = _by_groups(joint_groups(guard), start, goal, leg_ok)
        if path is not None:
            return Detour(tuple(path), "groups", checks)
        rng = np.random.default_rng(config.seed)
        path = _rrt_connect(guard, start, goal, leg_ok, rng, config)
        return Detour(tuple(_shortcut(path, leg_ok, rng, config.shortcuts)), "rrt", checks)
    except _OutOfBudget:
        return Detour(
            (),
            "",
            checks,
            f"no guarded path found within {checks} checks / {config.budget_s:g} s",
        )


def _by_groups(
    groups: Sequence[np.ndarray],
    start: np.ndarray,
    goal: np.ndarray,
    leg_ok: Callable[[np.ndarray, np.ndarray], bool],
) -> list[np.ndarray] | None:
    """Move the groups that differ one at a time, trying every order; legs already found
    safe (or not) are remembered."""
    moving = [g for g in groups if not np.array_equal(start[g], goal[g])]
    known: dict[tuple[frozenset, int], bool] = {}
    for order in itertools.permutations(range(len(moving))):
        q, done, path = start.copy(), frozenset(), []
        for k in order:
            key = (done, k)
            nxt = q.copy()
            nxt[moving[k]] = goal[moving[k]]
            if key not in known:
                known[key] = leg_ok(q, nxt)
            if not known[key]:
                break
            q, done = nxt, done | {k}
            path.append(nxt)
        else:
            return path
    return None


def _rrt_connect(
    guard: CollisionGuard,
    start: np.ndarray,
    goal: np.ndarray,
    leg_ok: Callable[[np.ndarray, np.ndarray], bool],
    rng: np.random.Generator,
    config: DetourConfig,
) -> list[np.ndarray]:
    """A path start .. goal (inclusive of goal, not of start); raises ``_OutOfBudget``."""
    lower = np.maximum(guard._lower, np.minimum(start, goal) - np.pi)
    upper = np.minimum(guard._upper, np.maximum(start, goal) + np.pi)
    trees = ([start], [goal])
    parents: tuple[list[int], list[int]] = ([-1], [-1])

    def steer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d = b - a
        far = float(np.max(np.abs(d)))
        return b.copy() if far <= config.rrt_step else a + d * (config.rrt_step / far)

    def extend(t: int, q: np.ndarray) -> int | None:
        nodes = trees[t]
        near = int(np.argmin([np.max(np.abs(n - q)) for n in nodes]))
        new = steer(nodes[near], q)
        a, b = (nodes[near], new) if t == 0 else (new, nodes[near])
        if not leg_ok(a, b):
            return None
        nodes.append(new)
        parents[t].append(near)
        return len(nodes) - 1

    def branch(t: int, i: int) -> list[np.ndarray]:
        out = []
        while i >= 0:
            out.append(trees[t][i])
            i = parents[t][i]
        return out

    t = 0
    while True:  # bounded by leg_ok's budget
        other = 1 - t
        if rng.random() < config.goal_bias:
            sample = trees[other][-1]
        else:
            sample = rng.uniform(lower, upper)
        i = extend(t, sample)
        if i is not None:
            target = trees[t][i]
            while True:  # connect: grow the other tree toward the new node
                j = extend(other, target)
                if j is None:
                    break
                if np.array_equal(trees[other][j], target):
                    a, b = (i, j) if t == 0 else (j, i)
                    path = branch(0, a)[::-1] + branch(1, b)[1:]
                    return path[1:]
        t = other


def _shortcut(
    path: list[np.ndarray],
    leg_ok: Callable[[np.ndarray, np.ndarray], bool],
    rng: np.random.Generator,
    attempts: int,
) -> list[np.ndarray]:
    """Drop waypoints whose neighbours see each other (the first point is the start, kept
    implicitly by the caller: ``path`` excludes it, so only interior points go)."""
    path = list(path)
    try:
        for _ in range(attempts):
            if len(path) < 3:
                break
            i = int(rng.integers(0, len(path) - 2))
            j = int(rng.integers(i + 2, len(path)))
            if leg_ok(path[i], path[j]):
                del path[i + 1 : j]
    except _OutOfBudget:
        pass
    return path
