"""Two arms' segments coordinated as DexMimicGen's constraints say (``datasets augment`` on a
bimanual or RX-1 source): a piece waits for the other arm's let-go of its object, and two
hands on one object share one transform."""

from __future__ import annotations

import numpy as np

from beavr_sim.datasets.augment.coordination import WORLD, coordinate, pieces_of
from beavr_sim.datasets.augment.segments import Segment


def handling(arm: str, obj: str, dest: str, frames: tuple[int, int, int, int, int]):
    a, b, c, d, e = frames
    return [
        Segment("approach", obj, obj, a, b, arm),
        Segment("grasp", obj, obj, b, c, arm),
        Segment("transport", obj, dest, c, d, arm),
        Segment("release", obj, dest, d, e, arm),
    ]


def test_a_relay_waits_for_the_other_arm_to_let_go():
    # left carries the item to the middle (lets go at 30); right picks it up there at 50.
    segments = handling("left", "item", "bin", (0, 10, 15, 30, 40)) + handling(
        "right", "item", "target", (0, 50, 55, 80, 100)
    )
    speed = {"item": np.zeros(100)}
    speed["item"][30:35] = 0.2  # it settles for 5 frames after the let-go
    pieces = coordinate(segments, speed)
    by = {(p.arm, p.reference): p for p in pieces}
    assert by["left", "item"].anchor == 0 and not by["left", "item"].waits_for
    right = by["right", "item"]
    assert (right.start, right.anchor, right.lead) == (0, 35, 15)
    assert right.waits_for == "left:item"
    assert by["right", "target"].anchor == 55  # its transport: no other arm before it
    assert all(p.group is None for p in pieces)  # never both hands on it at once


def test_one_arm_has_no_constraints():
    segments = handling("right", "item", "target", (0, 10, 15, 30, 40)) + handling(
        "right", "cube", "item", (40, 50, 55, 80, 100)
    )
    assert coordinate(segments) == pieces_of(segments)
    assert [p.anchor for p in pieces_of(segments)] == [0, 15, 40, 55]


def test_both_hands_on_one_object_share_its_transforms():
    segments = handling("left", "box", "target", (0, 10, 20, 50, 60)) + handling(
        "right", "box", "target", (0, 12, 20, 48, 60)
    )
    pieces = coordinate(segments)
    groups = {(p.arm, p.reference): p.group for p in pieces}
    assert groups["left", "box"] is not None
    assert groups["left", "box"] == groups["right", "box"]
    assert groups["left", "target"] == groups["right", "target"] != groups["left", "box"]
    assert all(not p.waits_for for p in pieces)  # held together, not one after the other


def test_a_placement_on_what_the_other_arm_set_down_waits_for_it():
    # StackBlocks on two arms: right sets the large block down at 150; left, holding the
    # small block since 60, places it on the large block (transport from 60 to 200).
    segments = handling("right", "large", "target", (0, 20, 30, 150, 170)) + handling(
        "left", "small", "large", (0, 50, 60, 200, 230)
    )
    pieces = coordinate(segments, {"large": np.zeros(230), "small": np.zeros(230)})
    by = {(p.arm, p.reference): p for p in pieces}
    assert (by["left", "large"].start, by["left", "large"].anchor) == (60, 150)
    assert by["left", "large"].waits_for == "right:large"
    assert by["left", "small"].anchor == 0


def test_an_arm_that_waits_in_the_source_waits_where_it_waited():
    # StackBlocks on two arms: left hovers until 367 while right places the large block; its
    # approach is carried with the small block only for the last 90 frames before the touch.
    segments = handling("right", "large", "target", (0, 158, 175, 267, 501)) + handling(
        "left", "small", "large", (0, 367, 378, 461, 501)
    )
    pieces = coordinate(segments)
    by = {(p.arm, p.reference): p for p in pieces}
    assert (by["left", "small"].anchor, by["left", "small"].lead) == (367 - 90, 90)
    assert by["right", "large"].anchor == 158 - 90
    assert by["right", "target"].anchor == 175  # a transport: carried from its start


def test_an_arm_done_placing_withdraws_as_in_the_source():
    # right places the large block and lets go at 267: 15 frames later it bridges back to its
    # own source palm (reference WORLD) over 60 frames; left after its own last let-go.
    segments = handling("right", "large", "target", (0, 158, 175, 267, 501)) + handling(
        "left", "small", "large", (0, 367, 378, 461, 501)
    )
    retreats = [p for p in coordinate(segments) if p.reference == WORLD]
    assert sorted((p.arm, p.anchor, p.lead, p.stop) for p in retreats) == [
        ("left", 461 + 15, 60, 501),
        ("right", 267 + 15, 60, 501),
    ]
    one_arm = handling("right", "item", "target", (0, 10, 15, 30, 40))
    assert all(p.reference != WORLD for p in coordinate(one_arm))
