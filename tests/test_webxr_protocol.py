"""The WebXR page's messages: strict parsing (every malformed message a counted reason, never
another exception), the HandFrame conversion and its round trip through the ``webxr25``
layout, and the twin geometry sent to the page."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from beavr_sim.headset.layouts import LAYOUTS
from beavr_sim.headset.webxr_protocol import (
    MAX_MESSAGE_BYTES,
    REASONS,
    HandsMessage,
    HelloMsg,
    SessionMsg,
    WebXRProtocolError,
    encode_hands,
    hand_frames,
    parse_message,
)
from beavr_sim.wire.hand import JOINT_INDEX, N_JOINTS

T_MS = 1.7e12  # a frame time on the page's clock (ms since the epoch)


def _hand_zup(seed: int = 0) -> np.ndarray:
    """A plausible canonical hand (26 joints, Z-up, metres) around (0.3, 0, 1.1)."""
    rng = np.random.default_rng(seed)
    return np.array([0.3, 0.0, 1.1]) + rng.uniform(-0.09, 0.09, size=(N_JOINTS, 3))


def _webxr(points_zup: np.ndarray) -> np.ndarray:
    return LAYOUTS["webxr25"].from_canonical(points_zup)


def _message(**overrides) -> dict:
    msg = json.loads(encode_hands(T_MS, {"right": _webxr(_hand_zup()), "left": None}, seq=1))
    msg.update(overrides)
    return msg


def _reason(payload) -> str:
    with pytest.raises(WebXRProtocolError) as info:
        parse_message(payload if isinstance(payload, (str, bytes)) else json.dumps(payload))
    assert info.value.reason in REASONS
    return info.value.reason


def test_round_trip_canonical_webxr_message_hand_frame():
    right, left = _hand_zup(0), _hand_zup(1)
    payload = encode_hands(
        T_MS, {"right": _webxr(right), "left": _webxr(left)}, seq=7, pinch={"left": True}
    )
    msg = parse_message(payload)
    assert isinstance(msg, HandsMessage) and msg.seq == 7 and msg.t_source == T_MS / 1e3
    frames = hand_frames(msg, t_receive=12.5)
    assert [f.side for f in frames] == ["right", "left"]
    palm = JOINT_INDEX["palm"]
    for frame, expected in zip(frames, (right, left), strict=True):
        assert frame.t_source == T_MS / 1e3 and frame.t_receive == 12.5
        others = np.arange(N_JOINTS) != palm
        np.testing.assert_allclose(frame.joints[others], expected[others], atol=1e-12)
        assert frame.tracked[others].all() and not frame.tracked[palm]  # palm is derived
        assert not frame.paused
    assert frames[1].pinch and not frames[0].pinch


def test_missing_hand_and_missing_joints_are_untracked_never_zeros():
    points = _webxr(_hand_zup())
    points[7] = np.nan  # index-finger-phalanx-intermediate: no pose this frame
    msg = parse_message(encode_hands(T_MS, {"right": points}, paused=True))
    right, left = hand_frames(msg, 1.0)
    assert not right.tracked[JOINT_INDEX["index_intermediate"]]
    assert np.isnan(right.joints[JOINT_INDEX["index_intermediate"]]).all()
    assert right.tracked.sum() == N_JOINTS - 2  # that joint and the derived palm
    assert not left.tracked.any() and np.isnan(left.joints).all()
    assert right.paused and left.paused and not left.pinch
    # "left": null is the same as no "left" key.
    msg_null = parse_message(encode_hands(T_MS, {"right": points, "left": None}))
    assert not hand_frames(msg_null, 1.0)[1].tracked.any()


def test_info_messages():
    hello = parse_message('{"v": 1, "type": "hello", "agent": "Quest Browser", "page": "1"}')
    assert isinstance(hello, HelloMsg) and hello.agent == "Quest Browser"
    session = parse_message('{"v": 1, "type": "session", "state": "started", "mode": "vr"}')
    assert isinstance(session, SessionMsg) and session.state == "started"


def _hand_field(field: str, values) -> dict:
    msg = _message()
    msg["hands"]["right"][field] = values
    return msg


MALFORMED = [
    (b'{"v": 1}', "binary"),
    ("x" * (MAX_MESSAGE_BYTES + 1), "too_long"),
    ("{not json", "not_json"),
    ('{"v": 1, "type": "hands", "t": NaN}', "not_json"),  # JSON has no NaN
    ('{"v": 1, "type": "hands", "t": 1e999}', "not_json"),  # out of range: no inf
    ("[1, 2]", "not_object"),
    ({"v": 2, "type": "hands"}, "unknown_version"),
    ({"type": "hands"}, "unknown_version"),
    ({"v": True, "type": "hello"}, "unknown_version"),
    ({"v": 1, "type": "pose"}, "unknown_type"),
    (_message(extra=1), "schema"),
    (_message(paused="no"), "schema"),
    (_message(seq=1.5), "schema"),
    ({k: v for k, v in _message().items() if k != "hands"}, "schema"),
    (_hand_field("pinch", "yes"), "schema"),
    (_hand_field("p", "1,2,3"), "schema"),
    (_message(t=-5.0), "bad_time"),
    (_message(t=0), "bad_time"),
    (_message(hands={"middle": None}), "unknown_hand"),
    (_hand_field("p", [0.1] * 74), "wrong_shape"),
    (_hand_field("q", [0.0, 0.0, 0.0, 1.0] * 24), "wrong_shape"),
    (_hand_field("r", [0.01] * 26), "wrong_shape"),
    (_hand_field("p", [None, 0.1, 0.2] + [0.1] * 72), "partial_joint"),
    (_hand_field("r", [None] + [0.01] * 24), "partial_joint"),
    (_hand_field("p", [11.0] * 75), "too_far"),
    (_hand_field("q", [0.0, 0.0, 0.0, 2.0] * 25), "bad_orientation"),
    (_hand_field("r", [0.0] * 25), "bad_radius"),
    (_hand_field("r", [0.5] * 25), "bad_radius"),
]


@pytest.mark.parametrize(("payload", "reason"), MALFORMED)
def test_malformed_messages_raise_with_their_reason(payload, reason):
    assert _reason(payload) == reason


def test_every_reason_is_tested():
    # The parametrized cases above name every reason the parser has (keep them in step).
    assert {reason for _, reason in MALFORMED} == set(REASONS)


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=6) | st.dictionaries(st.text(max_size=6), children, max_size=6)
    ),
    max_leaves=30,
)


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        st.text(max_size=200),
        st.binary(max_size=50),
        _json.map(json.dumps),
        st.fixed_dictionaries(
            {"v": st.just(1), "type": st.just("hands")},
            optional={
                "seq": _json,
                "t": _json,
                "paused": _json,
                "hands": _json,
            },
        ).map(json.dumps),
    )
)
def test_parser_only_ever_raises_protocol_errors(payload):
    try:
        msg = parse_message(payload)
    except WebXRProtocolError as err:
        assert err.reason in REASONS
        return
    if isinstance(msg, HandsMessage):
        for frame in hand_frames(msg, 0.0):  # whatever parsed converts
            assert frame.joints.shape == (N_JOINTS, 3)


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.booleans(), min_size=25, max_size=25),
    st.floats(1.0, 2e12),
    st.sampled_from(["right", "left"]),
)
def test_any_subset_of_joints_round_trips(has_pose, t_ms, side):
    points = _webxr(_hand_zup())
    points[~np.array(has_pose)] = np.nan
    frames = hand_frames(parse_message(encode_hands(t_ms, {side: points})), 0.0)
    frame = next(f for f in frames if f.side == side)
    canonical, tracked = LAYOUTS["webxr25"].to_canonical(points)
    np.testing.assert_array_equal(frame.tracked, tracked)
    np.testing.assert_allclose(frame.joints[tracked], canonical[tracked])
    assert frame.t_source == t_ms / 1e3


def test_twin_geometry_messages():
    import gymnasium as gym

    import beavr_sim  # noqa: F401
    from beavr_sim.headset.webxr_scene import TwinGeometry

    env = gym.make("beavr_sim/Pour-v0").unwrapped
    env.reset(seed=0)
    geometry = TwinGeometry.from_model(env.render_model)
    n = len(geometry.geom_ids)
    shapes = {"box", "sphere", "capsule", "cylinder", "ellipsoid", "mesh"}
    assert n > 20 and set(geometry.shapes) <= shapes  # meshes: tests/test_webxr_scene.py
    scene = json.loads(
        json.dumps(geometry.scene_message(env.data, task="Pour"), default=lambda a: a.tolist())
    )
    assert scene["type"] == "scene" and scene["task"] == "Pour"
    assert len(scene["pose"]) == 12 * n and len(scene["sizes"]) == 3 * n
    assert 0 < len(geometry.dynamic) < n  # the table does not move, the arm does
    twin = geometry.twin_message(env.data, 1.25, paused=False, holds={})
    assert twin["pose"].shape == (12 * len(geometry.dynamic),)
    # Poses are the world poses of the geoms: position then R_world_geom row by row.
    g = geometry.geom_ids[0]
    pose = geometry.poses(env.data)[0]
    np.testing.assert_allclose(pose[:3], env.data.geom_xpos[g])
    np.testing.assert_allclose(pose[3:], env.data.geom_xmat[g])
    env.close()
