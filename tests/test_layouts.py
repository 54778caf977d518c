from __future__ import annotations

import numpy as np
import pytest

from beavr_sim.headset.layouts import (
    LAYOUTS,
    METACARPAL_BASE_FRACTION,
    R_ZUP_UNITY,
    R_ZUP_WEBXR,
    get_layout,
    mediapipe21,
    to_hand_frame,
    unity_to_zup,
    webxr_to_zup,
    zup_to_unity,
    zup_to_webxr,
)
from beavr_sim.naming import UnknownNameError
from beavr_sim.operator.palm import R_world_palm, keypoints_in_palm
from beavr_sim.wire.hand import JOINT_INDEX, JOINT_NAMES, N_JOINTS

J = JOINT_INDEX
FOUR = ("index", "middle", "ring", "little")


def rest_hand_flu(side: str) -> np.ndarray:
    """A flat hand, palm down, fingers forward: 26 joints as (forward, left, up) metres."""
    hand = np.zeros((N_JOINTS, 3))
    thumb = ((0.02, 0.02, -0.01), (0.045, 0.045, -0.015), (0.07, 0.06, -0.02), (0.09, 0.07, -0.025))
    for name, p in zip(("metacarpal", "proximal", "distal", "tip"), thumb, strict=True):
        hand[J[f"thumb_{name}"]] = p
    for finger, y in zip(FOUR, (0.022, 0.0, -0.018, -0.034), strict=True):
        knuckle = np.array([0.09, y, 0.0])
        hand[J[f"{finger}_metacarpal"]] = 0.3 * knuckle
        hand[J[f"{finger}_proximal"]] = knuckle
        for k, name in enumerate(("intermediate", "distal", "tip"), start=1):
            hand[J[f"{finger}_{name}"]] = knuckle + [0.03 * k, 0.0, -0.004 * k]
    hand[J["palm"]] = 0.5 * (hand[J["middle_metacarpal"]] + hand[J["middle_proximal"]])
    if side == "left":
        hand[:, 1] *= -1.0
    return hand


def rest_hand_unity(side: str) -> np.ndarray:
    """The same hand written directly in Unity axes: x right, y up, z forward."""
    flu = rest_hand_flu(side)
    return np.column_stack([-flu[:, 1], flu[:, 2], flu[:, 0]])


def test_unity_conversion_is_a_reflection_with_the_documented_axes():
    assert np.linalg.det(R_ZUP_UNITY) == pytest.approx(-1.0)
    forward, right, up = np.eye(3)[2], np.eye(3)[0], np.eye(3)[1]
    np.testing.assert_array_equal(unity_to_zup(forward), [1, 0, 0])
    np.testing.assert_array_equal(unity_to_zup(right), [0, -1, 0])
    np.testing.assert_array_equal(unity_to_zup(up), [0, 0, 1])
    points = np.random.default_rng(0).normal(size=(4, 5, 3))
    np.testing.assert_array_equal(zup_to_unity(unity_to_zup(points)), points)
    np.testing.assert_array_equal(unity_to_zup(zup_to_unity(points)), points)


def test_webxr_conversion_is_a_rotation_with_the_documented_axes():
    assert np.linalg.det(R_ZUP_WEBXR) == pytest.approx(1.0)
    np.testing.assert_array_equal(webxr_to_zup([0, 0, -1]), [1, 0, 0])  # -z forward
    np.testing.assert_array_equal(webxr_to_zup([1, 0, 0]), [0, -1, 0])  # x right
    np.testing.assert_array_equal(webxr_to_zup([0, 1, 0]), [0, 0, 1])  # y up
    points = np.random.default_rng(1).normal(size=(7, 3))
    np.testing.assert_array_equal(zup_to_webxr(webxr_to_zup(points)), points)


def test_layout_sizes():
    assert {name: layout.n_joints for name, layout in LAYOUTS.items()} == {
        "quest26": 26,
        "ovr24": 24,
        "mediapipe21": 21,
        "webxr25": 25,
    }
    assert LAYOUTS["webxr25"].derived_joints == ("palm",)
    assert set(LAYOUTS["ovr24"].derived_joints) == {
        "palm",
        "index_metacarpal",
        "middle_metacarpal",
        "ring_metacarpal",
    }


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_canonical_to_layout_to_canonical(name):
    layout = LAYOUTS[name]
    joints = rest_hand_flu("right")
    back, tracked = layout.to_canonical(layout.from_canonical(joints))
    assert np.isfinite(back).all()
    derived = [J[n] for n in layout.derived_joints]
    assert not tracked[derived].any()
    assert tracked.sum() == N_JOINTS - len(derived)
    np.testing.assert_allclose(back[tracked], joints[tracked], atol=1e-12)


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_layout_to_canonical_to_layout_is_exact(name):
    layout = LAYOUTS[name]
    points = np.random.default_rng(2).uniform(-0.3, 0.3, size=(layout.n_joints, 3))
    again = layout.from_canonical(layout.to_canonical(points)[0])
    kept = [i for i, c in enumerate(layout.canonical_names) if c is not None]
    np.testing.assert_array_equal(again[kept], points[kept])
    if name == "ovr24":  # forearm stub at the wrist, trapezium halfway to thumb1
        names = layout.joint_names
        np.testing.assert_allclose(again[names.index("forearm_stub")], points[0])
        thumb0 = 0.5 * (points[0] + points[names.index("thumb1")])
        np.testing.assert_allclose(again[names.index("thumb0")], thumb0, atol=1e-15)
    else:
        np.testing.assert_array_equal(again, points)


def test_mediapipe_rotation_argument():
    angle = 0.7
    c, s = np.cos(angle), np.sin(angle)
    R_zup_source = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    )
    layout = mediapipe21(R_zup_source)
    points = np.random.default_rng(3).normal(size=(21, 3))
    joints, _ = layout.to_canonical(points)
    np.testing.assert_allclose(joints[J["index_tip"]], R_zup_source @ points[8], atol=1e-15)
    np.testing.assert_allclose(layout.from_canonical(joints), points, atol=1e-14)
    with pytest.raises(ValueError, match="det"):
        mediapipe21(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="rotation"):
        mediapipe21(np.diag([1.0, 2.0, 1.0]))


def test_derived_joints_follow_the_documented_rule():
    points = np.random.default_rng(4).normal(size=(24, 3))
    joints, tracked = LAYOUTS["ovr24"].to_canonical(points)
    wrist = joints[J["wrist"]]
    for finger in ("index", "middle", "ring"):
        expected = wrist + METACARPAL_BASE_FRACTION * (joints[J[f"{finger}_proximal"]] - wrist)
        np.testing.assert_allclose(joints[J[f"{finger}_metacarpal"]], expected, atol=1e-15)
    # little metacarpal is an OVR bone (pinky0): converted, not derived
    np.testing.assert_array_equal(joints[J["little_metacarpal"]], unity_to_zup(points[15]))
    assert tracked[J["little_metacarpal"]]
    palm = 0.5 * (joints[J["middle_metacarpal"]] + joints[J["middle_proximal"]])
    np.testing.assert_allclose(joints[J["palm"]], palm, atol=1e-15)


def test_batches_and_untracked_source_joints():
    layout = LAYOUTS["webxr25"]
    points = np.random.default_rng(5).normal(size=(3, 2, 25, 3))
    points[1, 0, 7] = np.nan
    joints, tracked = layout.to_canonical(points)
    assert joints.shape == (3, 2, 26, 3) and tracked.shape == (3, 2, 26)
    one, one_tracked = layout.to_canonical(points[2, 1])
    np.testing.assert_array_equal(joints[2, 1], one)
    np.testing.assert_array_equal(tracked[2, 1], one_tracked)
    assert not tracked[1, 0, J["index_intermediate"]]  # webxr joint 7
    assert np.isnan(joints[1, 0, J["index_intermediate"]]).all()
    assert tracked[1, 0].sum() == 24  # minus the derived palm and the lost joint


def test_bad_input_errors():
    with pytest.raises(ValueError, match=r"'ovr24'.*\(\.\.\., 24, 3\).*\(26, 3\)"):
        LAYOUTS["ovr24"].to_canonical(np.zeros((26, 3)))
    with pytest.raises(ValueError, match=r"'quest26'.*\(\.\.\., 26, 3\)"):
        LAYOUTS["quest26"].from_canonical(np.zeros((24, 3)))
    with pytest.raises(UnknownNameError, match="quest26"):
        get_layout("quest24")
    with pytest.raises(UnknownNameError):
        to_hand_frame("openxr26", np.zeros((26, 3)), "right", 0.0, 0.0)
    with pytest.raises(ValueError, match="one hand"):
        to_hand_frame("quest26", np.zeros((2, 26, 3)), "right", 0.0, 0.0)


@pytest.mark.parametrize("side", ["right", "left"])
def test_unity_hand_gives_a_proper_palm_frame(side):
    frame = to_hand_frame(
        "quest26", rest_hand_unity(side), side, 1.0, 1.5, resolution="low", paused=True
    )
    assert (frame.resolution, frame.paused, frame.t_source) == ("low", True, 1.0)
    R_world_palm_ = R_world_palm(frame.joints, side)
    np.testing.assert_allclose(R_world_palm_.T @ R_world_palm_, np.eye(3), atol=1e-12)
    assert np.linalg.det(R_world_palm_) == pytest.approx(1.0)
    # palm down, fingers forward: palmar normal (x) is world -z, fingers (z) world +x
    np.testing.assert_allclose(R_world_palm_[:, 0], [0, 0, -1], atol=1e-9)
    np.testing.assert_allclose(R_world_palm_[:, 2], [1, 0, 0], atol=1e-9)
    in_palm = keypoints_in_palm(frame.joints, side)
    thumb_y = in_palm[J["thumb_tip"], 1]
    assert thumb_y > 0.05 if side == "right" else thumb_y < -0.05
    # the thumb of a right hand is on the world left (+y)
    assert np.sign(frame.position("thumb_tip")[1]) == (1 if side == "right" else -1)


def test_real_human_trace_converts(reference_dir):
    path = reference_dir / "human_hand_trace" / "human_joint_right_mediapipe21.npz"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    keypoints = np.load(path)["keypoints"]
    assert keypoints.shape == (621, 21, 3)
    joints, tracked = LAYOUTS["mediapipe21"].to_canonical(keypoints)
    assert np.isfinite(joints).all()
    assert (tracked.sum(axis=1) == 21).all()
    frame = to_hand_frame("mediapipe21", keypoints[100], "right", 0.0, 0.0)
    np.testing.assert_array_equal(frame.joints, joints[100])
    tips = [J[f"{f}_tip"] for f in FOUR]
    for hand in joints[::5]:
        R = R_world_palm(hand, "right")
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        in_palm = keypoints_in_palm(hand, "right")
        assert (in_palm[tips, 2] > 0.03).all()  # fingertips beyond the wrist, along +z
        assert in_palm[J["thumb_proximal"], 1] > 0.01  # right thumb on +y
        # a right hand in a right-handed frame flexes its fingers to the palmar side (+x);
        # a mirrored conversion would put them on -x
        assert (in_palm[tips, 0] > 0.0).all()
    names = [JOINT_NAMES[i] for i in np.flatnonzero(~tracked[0])]
    assert sorted(names) == sorted(LAYOUTS["mediapipe21"].derived_joints)
