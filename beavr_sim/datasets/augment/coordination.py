"""Pieces of every arm and the constraints between arms (DexMimicGen's, for two arms).

A *piece* is a run of one arm's consecutive segments with the same reference (approach and
grasp of an object; transport and release to its destination): it moves rigidly with that
reference, its transform taken at its *anchor* frame (:mod:`.execute`). All arms follow one
clock, the source's frame index, so what the source did at the same time is done at the same
time (lockstep). Two constraints between arms, as in DexMimicGen:

- **Sequential**: an arm's piece carried in the frame of an object another arm handled before
  it (the source ordered them: the other arm let go of the object after this piece began and
  before the end of the piece's first segment: this arm's first touch of it, or its placement
  on it) waits: its anchor is where the other arm let go and the object came to rest (speed
  under :attr:`CoordinationRules.still_speed`), not the piece's start.
  Until then the arm keeps its previous transform; its bridge starts from there. A relay (one
  arm sets the object down, the other picks it up) is therefore grasped where the object was
  set down in the new scene, not where it stood at the reset.
- **Coordination**: handlings of one object by two arms that overlap in time (both hands hold
  it) share one transform: the pieces of both with the same reference form a group, and the
  first of the group to reach its anchor decides the transform for all.

- **Idle arm**: with two arms, an approach is carried in its object's frame for at most
  :attr:`CoordinationRules.approach_frames` before the first touch. An arm that waits in the
  source (one hand hovers while the other places the large block) waits where it waited in
  the source, not moved with an object it touches seconds later: carried early, the waiting
  hand drifts towards the middle with its object and meets the other arm there.

- **Retreat**: with two arms, an arm's last release (its hand leaving what it placed, to the
  episode's end) is carried in the destination's frame for
  :attr:`CoordinationRules.retreat_hold` frames, then bridges back to the source's own palm
  (a piece with reference :data:`WORLD`, transform identity) over
  :attr:`CoordinationRules.retreat_frames`: the hand withdraws to where it withdrew in the
  source, on its own side, instead of to that place turned about the destination (StackBlocks:
  a withdrawal 28 cm from the target area's centre, the area turned 45 degrees, moves 21 cm,
  into the other arm's way).

With one arm there are no constraints: every piece is anchored at its start.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from beavr_sim.datasets.augment.segments import Segment

HELD = ("grasp", "transport")  # segments in which the arm touches its object
WORLD = ""  # the reference of a retreat piece: the world (the source's palm, untransformed)


@dataclass(frozen=True)
class CoordinationRules:
    still_speed: float = 0.05  # m/s: a let-go object has come to rest
    approach_frames: int = 90  # with two arms, the longest an approach is carried (frames)
    retreat_hold: int = 15  # frames after a last let-go still carried with the destination
    retreat_frames: int = 60  # frames over which the retreat's bridge runs (its lead)


@dataclass(frozen=True)
class Piece:
    arm: str
    reference: str
    start: int  # first frame
    stop: int  # one past the last frame
    anchor: int  # the frame at which its transform is taken (its start unless it waits)
    lead: int  # frames from the anchor to the end of its first segment (the bridge's room)
    group: int | None = None  # pieces of one group share one transform (coordination)
    waits_for: str = ""  # "arm:object" whose let-go it waits for (sequential), or ""


def pieces_of(segments: list[Segment]) -> list[Piece]:
    """Per arm, consecutive segments with the same reference, joined; anchored at their
    start (no constraints)."""
    out: list[Piece] = []
    last: dict[str, int] = {}
    for seg in segments:
        k = last.get(seg.arm)
        prev = out[k] if k is not None else None
        if prev is not None and prev.reference == seg.reference and prev.stop == seg.start:
            out[k] = Piece(seg.arm, seg.reference, prev.start, seg.stop, prev.anchor, prev.lead)
        else:
            last[seg.arm] = len(out)
            out.append(Piece(seg.arm, seg.reference, seg.start, seg.stop, seg.start,
                             seg.stop - seg.start))  # fmt: skip
    return out


@dataclass(frozen=True)
class _Handling:
    arm: str
    object: str
    first_touch: int
    let_go: int  # one past the last touch


def _handlings(segments: list[Segment]) -> list[_Handling]:
    spans: dict[tuple[str, str, int], list[int]] = {}
    order = 0
    for seg in segments:  # an arm's handlings of one object are separated by its approach
        if seg.kind == "approach":
            order += 1
        if seg.kind in HELD:
            key = (seg.arm, seg.object, order)
            a, b = spans.get(key, [seg.start, seg.stop])
            spans[key] = [min(a, seg.start), max(b, seg.stop)]
    return [_Handling(arm, obj, a, b) for (arm, obj, _), (a, b) in spans.items()]


def coordinate(
    segments: list[Segment],
    speed: Mapping[str, np.ndarray] | None = None,
    rules: CoordinationRules | None = None,
) -> list[Piece]:
    """Every arm's pieces with their anchors and groups (see the module docstring);
    ``speed`` (object -> per-frame speed) tells when a let-go object is at rest."""
    rules = rules or CoordinationRules()
    by_arm: dict[str, list[Segment]] = {}
    for seg in sorted(segments, key=lambda s: s.start):
        by_arm.setdefault(seg.arm, []).append(seg)
    handlings = _handlings([s for arm in by_arm.values() for s in arm])
    pieces: list[Piece] = []
    for arm_segments in by_arm.values():
        pieces += pieces_of(arm_segments)
    out: list[Piece] = []
    for piece in pieces:
        # the end of its first segment: the first touch (an approach), the placement (a transport)
        first = next(s for s in by_arm[piece.arm] if s.start >= piece.start)
        first_stop = first.stop
        if len(by_arm) > 1 and first.kind == "approach" and piece.lead > rules.approach_frames:
            anchor = first_stop - rules.approach_frames  # idle until then (see the docstring)
            piece = Piece(piece.arm, piece.reference, piece.start, piece.stop, anchor,
                          first_stop - anchor, piece.group, piece.waits_for)  # fmt: skip
        before = [
            h for h in handlings
            if h.arm != piece.arm and h.object == piece.reference
            and piece.start < h.let_go <= first_stop
        ]  # fmt: skip
        if not before:
            out.append(piece)
            continue
        other = max(before, key=lambda h: h.let_go)
        anchor = max(other.let_go, piece.anchor)
        if speed is not None and piece.reference in speed:
            moving = speed[piece.reference]
            while anchor < first_stop - 1 and moving[anchor] >= rules.still_speed:
                anchor += 1
        anchor = min(anchor, first_stop - 1)
        out.append(Piece(piece.arm, piece.reference, piece.start, piece.stop, anchor,
                         first_stop - anchor, None, f"{other.arm}:{other.object}"))  # fmt: skip
    if len(by_arm) > 1:
        out += _retreats(by_arm, rules)
    return _group(out, handlings)


def _retreats(by_arm: Mapping[str, list[Segment]], rules: CoordinationRules) -> list[Piece]:
    """Per arm whose last segment is a release to the end, a retreat piece (see the module
    docstring)."""
    out = []
    end = max(s.stop for segs in by_arm.values() for s in segs)
    for arm, segments in by_arm.items():
        last = segments[-1]
        anchor = last.start + rules.retreat_hold
        if last.kind == "release" and last.stop == end and anchor < end:
            out.append(Piece(arm, WORLD, anchor, end, anchor, rules.retreat_frames))
    return out


def _group(pieces: list[Piece], handlings: list[_Handling]) -> list[Piece]:
    """Pieces of two arms with one reference that cover overlapping handlings of one object
    get one group."""
    groups: dict[int, int] = {}
    next_group = 0
    for i, a in enumerate(pieces):
        for j in range(i + 1, len(pieces)):
            b = pieces[j]
            if a.arm == b.arm or a.reference != b.reference:
                continue
            if any(
                ha.arm == a.arm and hb.arm == b.arm and ha.object == hb.object
                and ha.first_touch < hb.let_go and hb.first_touch < ha.let_go
                and _covers(a, ha) and _covers(b, hb)
                for ha in handlings for hb in handlings
            ):  # fmt: skip
                g = groups.get(i, groups.get(j))
                if g is None:
                    g, next_group = next_group, next_group + 1
                groups[i] = groups[j] = g
    return [
        Piece(p.arm, p.reference, p.start, p.stop, p.anchor, p.lead, groups.get(i), p.waits_for)
        for i, p in enumerate(pieces)
    ]


def _covers(piece: Piece, handling: _Handling) -> bool:
    return piece.start < handling.let_go and handling.first_touch < piece.stop
