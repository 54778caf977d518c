"""Object-centric segments of a replayed source episode, found from contacts and motion.

Per arm (effector): a *handling* of an object is a run of frames in which the arm touches it (runs less than
:attr:`SegmentRules.merge_gap` frames apart are one run) and during which it moves more than
:attr:`SegmentRules.min_travel`: touches that do not move the object (brushing past it) are
not handlings. An arm's handlings are taken in the order they start. Each is split into four
segments of that arm:

- ``approach``: from the end of the arm's previous handling's release (the episode's start for
  the first) to the first touch; reference: the object;
- ``grasp``: first touch until the object starts to move (:attr:`SegmentRules.moved`);
  reference: the object;
- ``transport``: the object moving in the hand until the last touch; reference: the
  *destination*, the other thing (free object or fixture) nearest to the object, in the
  table plane, where it was let go; with no other thing, the object itself where it was
  picked up;
- ``release``: after the last touch, up to half way to the arm's next handling's first touch
  (or the episode's end); reference: the destination.

The arms' segments are returned together, ordered by start frame; how two arms' segments are
ordered and synchronised when executed is :mod:`.coordination`'s.

Where it fails (the error names the source episode): a source in which the robot never moves
an object by touching it (nothing to carry); an object moved by another object (a tool, a
push with a held block) is not handled by the robot, so no segment is made for it; two
objects held at once by one arm (their runs overlap) are two handlings sharing frames,
refused; a release far from any thing picks the nearest all the same.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from beavr_sim.datasets.augment.replay import Trajectory

KINDS = ("approach", "grasp", "transport", "release")


class SegmentationError(ValueError):
    """The source episode cannot be split into segments (the reason says why)."""


@dataclass(frozen=True)
class SegmentRules:
    merge_gap: int = 10  # frames: touch runs closer than this are one run
    min_travel: float = 0.02  # m: a handling moves its object at least this far
    moved: float = 0.005  # m: the object has started to move


@dataclass(frozen=True)
class Segment:
    kind: str  # one of KINDS
    object: str  # the handled object
    reference: str  # the thing whose frame carries the palm trajectory
    start: int  # first frame
    stop: int  # one past the last frame
    arm: str = ""  # the effector whose palm this segment carries


def _runs(mask: np.ndarray, merge_gap: int) -> list[tuple[int, int]]:
    idx = np.flatnonzero(mask)
    if not len(idx):
        return []
    runs, start, last = [], int(idx[0]), int(idx[0])
    for i in idx[1:]:
        if i - last > merge_gap:
            runs.append((start, last + 1))
            start = int(i)
        last = int(i)
    runs.append((start, last + 1))
    return runs


def _destination(traj: Trajectory, obj: str, frame: int) -> str:
    here = traj.pos[obj][frame][:2]
    others = [t for t in traj.things.names if t != obj]
    if not others:
        return obj
    return min(others, key=lambda t: float(np.linalg.norm(traj.pos[t][frame][:2] - here)))


def find_segments(traj: Trajectory, rules: SegmentRules | None = None) -> list[Segment]:
    """Every arm's segments of ``traj``, ordered by start (see the module docstring); an
    episode in which no arm moves an object by touching it is refused."""
    rules = rules or SegmentRules()
    segments = [s for arm in traj.arms for s in arm_segments(traj, arm, rules)]
    if not segments:
        name = f"source episode {traj.episode.index} (seed {traj.episode.seed})"
        raise SegmentationError(f"{name}: the robot never moves an object by touching it")
    return sorted(segments, key=lambda s: (s.start, traj.arms.index(s.arm)))


def arm_segments(traj: Trajectory, arm: str, rules: SegmentRules) -> list[Segment]:
    """The segments of ``arm`` in order; none when it handles nothing."""
    handlings: list[tuple[int, int, str]] = []
    for obj in traj.things.objects:
        for c0, c1 in _runs(traj.touch[arm][obj], rules.merge_gap):
            travel = np.linalg.norm(traj.pos[obj][c0:c1] - traj.pos[obj][c0], axis=1)
            if travel.max(initial=0.0) >= rules.min_travel:
                handlings.append((c0, c1, obj))
    handlings.sort()
    name = f"source episode {traj.episode.index} (seed {traj.episode.seed})"
    for (_, b1, o1), (a2, _, o2) in pairwise(handlings):
        if a2 < b1:
            raise SegmentationError(f"{name}: {o1} and {o2} are held at once by {arm}")
    segments: list[Segment] = []
    begin = 0
    for k, (c0, c1, obj) in enumerate(handlings):
        travel = np.linalg.norm(traj.pos[obj][c0:c1] - traj.pos[obj][c0], axis=1)
        moving = c0 + int(np.argmax(travel > rules.moved))
        end = (c1 + handlings[k + 1][0]) // 2 if k + 1 < len(handlings) else traj.frames
        destination = _destination(traj, obj, c1 - 1)
        for kind, a, b, ref in (
            ("approach", begin, c0, obj),
            ("grasp", c0, moving, obj),
            ("transport", moving, c1, destination),
            ("release", c1, end, destination),
        ):
            if b > a:
                segments.append(Segment(kind, obj, ref, a, b, arm))
        begin = end
    return segments
