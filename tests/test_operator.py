"""Operator pieces: palm frame, relative arm mapping, filters, and the operator's session rules."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from beavr_sim.naming import UnknownNameError
from beavr_sim.operator.arm_mapping import AxisMap, RelativeMotionMapping, axis_map
from beavr_sim.operator.filters import (
    MIN_DT,
    KeypointFilter,
    PoseFilter,
    lowpass_gain,
    slerp,
    so3_exp,
    so3_log,
)
from beavr_sim.operator.operator import MAX_PENDING_GESTURES, Operator, OperatorConfig
from beavr_sim.operator.palm import R_world_palm, T_world_palm, keypoints_in_palm
from beavr_sim.operator.retarget import human_keypoints_for
from beavr_sim.robots import make_embodiment
from beavr_sim.wire.hand import HandFrame

rng = np.random.default_rng(0)


def random_rotation(rng) -> np.ndarray:
    return so3_exp(rng.normal(size=3) * 1.2)


def random_pose(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = rng.normal(size=3) * 0.3
    return T


def hand_joints(T_world_palm_: np.ndarray, side: str = "right", q_hand=None) -> np.ndarray:
    kp = human_keypoints_for(np.zeros(16) if q_hand is None else q_hand, side)
    return kp @ T_world_palm_[:3, :3].T + T_world_palm_[:3, 3]


def palm_down(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]])
    T[:3, 3] = p
    return T


# ------------------------------------------------------------------------------- palm frame
@pytest.mark.parametrize("side", ["right", "left"])
def test_palm_frame_is_orthonormal_and_follows_the_hand(side):
    for _ in range(20):
        T = random_pose(rng)
        joints = hand_joints(T, side)
        T_est = T_world_palm(joints, side)
        np.testing.assert_allclose(T_est, T, atol=1e-9)
        R = R_world_palm(joints, side)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(
            keypoints_in_palm(joints, side), human_keypoints_for(np.zeros(16), side), atol=1e-9
        )


def test_right_thumb_is_on_plus_y_and_left_on_minus_y():
    for side, sign in (("right", 1), ("left", -1)):
        kp = human_keypoints_for(np.zeros(16), side)
        assert sign * kp[3, 1] > 0.01  # thumb_proximal


def test_degenerate_hand_raises():
    with pytest.raises(ValueError, match="degenerate"):
        R_world_palm(np.zeros((26, 3)), "right")


# ------------------------------------------------------------------------------- mapping
def test_mapping_is_identity_at_the_anchor_and_round_trips():
    m = RelativeMotionMapping(axis_map("xarm7_leap_right", "right"))
    with pytest.raises(RuntimeError, match="anchor"):
        m.robot_target(np.eye(4))
    H0, R0 = random_pose(rng), random_pose(rng)
    m.anchor(H0, R0)
    np.testing.assert_allclose(m.robot_target(H0), R0, atol=1e-12)
    for res in ("high", "low"):
        H = random_pose(rng)
        np.testing.assert_allclose(m.hand_for(m.robot_target(H, res), res), H, atol=1e-9)


def test_mapping_moves_the_robot_as_the_hand_moves_in_its_own_frame():
    m = RelativeMotionMapping(AxisMap())
    H0, R0 = palm_down([0.3, -0.2, 1.0]), palm_down([0.4, 0.0, 0.9])
    m.anchor(H0, R0)
    H = H0.copy()
    H[:3, 3] += [0.05, 0.02, -0.03]  # palm frames aligned: the same world displacement
    np.testing.assert_allclose(
        m.robot_target(H)[:3, 3] - R0[:3, 3], [0.05, 0.02, -0.03], atol=1e-12
    )
    np.testing.assert_allclose(
        m.robot_target(H, "low")[:3, 3] - R0[:3, 3], 0.6 * np.array([0.05, 0.02, -0.03]), atol=1e-12
    )


def test_axis_map_rejects_reflections_and_unknown_embodiments():
    with pytest.raises(ValueError, match="det"):
        AxisMap(A_rot=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="Valid"):
        axis_map("no_such_robot", "right")


# ------------------------------------------------------------------------------- filters
def test_so3_log_exp_round_trip_including_near_pi():
    for angle in (1e-9, 0.3, 2.0, np.pi - 1e-6):
        axis = rng.normal(size=3)
        w = axis / np.linalg.norm(axis) * angle
        R = so3_exp(w)
        np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-6)


def test_slerp_endpoints_and_midpoint():
    Ra, Rb = random_rotation(rng), random_rotation(rng)
    np.testing.assert_allclose(slerp(Ra, Rb, 0.0), Ra, atol=1e-12)
    np.testing.assert_allclose(slerp(Ra, Rb, 1.0), Rb, atol=1e-9)
    mid = slerp(Ra, Rb, 0.5)
    d1 = np.linalg.norm(so3_log(Ra.T @ mid))
    d2 = np.linalg.norm(so3_log(mid.T @ Rb))
    assert d1 == pytest.approx(d2, abs=1e-9)


def test_keypoint_filter_is_a_one_euro_filter_per_joint():
    """At rest it is a low-pass of cutoff min_cutoff_hz; speed raises the cutoff."""
    f = KeypointFilter(min_cutoff_hz=2.0, beta=0.0, d_cutoff_hz=1.0)
    valid = np.ones(26, dtype=bool)
    np.testing.assert_array_equal(f(np.full((26, 3), 3.0), valid, 0.0), 3.0)  # starts there
    tau = 1 / (2 * np.pi * 2.0)
    out = f(np.full((26, 3), 6.0), valid, 0.05)
    np.testing.assert_allclose(out, 3.0 + 3.0 * 0.05 / (0.05 + tau))
    assert f.lag_at_rest_s == pytest.approx(tau)
    slow, fast = KeypointFilter(2.0, beta=0.0), KeypointFilter(2.0, beta=10.0)
    for k in range(10):  # a joint moving at 1.7 m/s
        x = np.full((26, 3), 0.01 * k)
        lag_slow = x[0, 0] - slow(x, valid, k / 100)[0, 0]
        lag_fast = x[0, 0] - fast(x, valid, k / 100)[0, 0]
    assert 0 < lag_fast < 0.5 * lag_slow  # a fast joint follows more closely
    for bad in ({"min_cutoff_hz": 0.0}, {"beta": -1.0}, {"d_cutoff_hz": float("nan")}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            KeypointFilter(**bad)
    with pytest.raises(ValueError, match="shape"):
        f(np.zeros((25, 3)), valid, 1.0)


def test_keypoint_filter_averages_each_joint_over_its_valid_samples_only():
    f = KeypointFilter()
    valid = np.ones(26, dtype=bool)
    x = np.tile(np.arange(26.0)[:, None], (1, 3)) * 0.01
    f(x, valid, 0.0)
    held = f(x, valid, 1 / 72)[10].copy()
    gap = valid.copy()
    gap[10] = False
    bad = x.copy()
    bad[10] = np.nan  # untracked: its value is meaningless
    for k in range(6):
        out = f(bad + 0.001 * k, gap, (2 + k) / 72)
        np.testing.assert_array_equal(out[10], held)  # holds its last filtered value
        assert np.isfinite(out).all()
    out = f(x + 0.01, valid, 8 / 72)  # back: finite, moving towards the new value
    assert np.isfinite(out).all() and (out[10] > held).all()
    fresh = KeypointFilter()
    never = valid.copy()
    never[3] = False
    assert np.isnan(fresh(bad, never, 0.0)[3]).all()  # never valid: NaN (flagged untracked)


@pytest.mark.parametrize("stamps", [(0.0, 0.0), (0.1, 0.05), (0.1, float("nan"))])
def test_filters_take_repeated_and_out_of_order_stamps_as_a_tiny_step(stamps):
    f, g = KeypointFilter(), PoseFilter()
    valid = np.ones(26, dtype=bool)
    f(np.zeros((26, 3)), valid, stamps[0])
    g(np.eye(4), stamps[0])
    out = f(np.ones((26, 3)), valid, stamps[1])
    assert np.isfinite(out).all() and 0.0 < out[0, 0] < 0.05  # a 72 Hz frame: 0.33
    T = g(palm_down([1.0, 0.0, 0.0]), stamps[1])
    assert np.isfinite(T).all() and 0.0 < T[0, 3] < 0.02
    assert lowpass_gain(-1.0, 0.01) == pytest.approx(MIN_DT / (MIN_DT + 0.01))


@pytest.mark.parametrize("rate_hz", [30.0, 60.0, 90.0])
def test_filters_lag_a_ramp_by_their_time_constant_at_any_rate(rate_hz):
    f, g = KeypointFilter(), PoseFilter()  # the defaults
    valid = np.ones(26, dtype=bool)
    speed = 0.2
    for k in range(int(2.0 * rate_hz) + 1):
        t = k / rate_hz
        out = f(np.full((26, 3), speed * t), valid, t)
        T = np.eye(4)
        T[:3, 3] = speed * t
        T_out = g(T, t)
    # The lag at this speed (per coordinate: |v| = sqrt(3) * speed).
    tau = 1 / (2 * np.pi * (f.min_cutoff_hz + f.beta * np.sqrt(3) * speed))
    assert (speed * t - out[0, 0]) / speed == pytest.approx(tau, abs=2e-4)
    assert (speed * t - T_out[0, 3]) / speed == pytest.approx(g.tau_position_s, abs=1e-9)


def test_pose_filter_moves_by_its_time_constant():
    with pytest.raises(ValueError, match="tau"):
        PoseFilter(-0.1)
    f = PoseFilter(0.05, 0.05)
    T0, T1 = np.eye(4), palm_down([1.0, 0, 0])
    np.testing.assert_allclose(f(T0, 0.0), T0)
    half = f(T1, 0.05)  # dt = tau: half way
    assert half[0, 3] == pytest.approx(0.5)
    for k in range(60):
        out = f(T1, 0.1 + k * 0.05)
    np.testing.assert_allclose(out, T1, atol=1e-9)
    follow = PoseFilter(0.0, 0.0)  # tau 0: no filtering
    follow(T0, 0.0)
    np.testing.assert_allclose(follow(T1, 0.01), T1, atol=1e-12)


def test_pose_filter_is_lerp_and_slerp_of_each_measurement():
    """The quaternion-state filter equals the matrix definition step by step."""
    f = PoseFilter(0.02, 0.005)
    T_expected = None
    t = 0.0
    for _ in range(20):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = random_rotation(rng), rng.normal(size=3)
        dt = rng.uniform(0.005, 0.04)
        t += dt
        out = f(T, t)
        if T_expected is None:
            T_expected = T.copy()
        else:
            T_expected[:3, 3] += dt / (dt + 0.02) * (T[:3, 3] - T_expected[:3, 3])
            T_expected[:3, :3] = slerp(T_expected[:3, :3], T[:3, :3], dt / (dt + 0.005))
        np.testing.assert_allclose(out, T_expected, atol=1e-9)
    f.reset(T, t)
    np.testing.assert_allclose(f(np.eye(4), t + 0.02)[:3, 3], 0.5 * T[:3, 3], atol=1e-12)


# ------------------------------------------------------------------------------- operator
DT = 1 / 30


@pytest.fixture(scope="module")
def operator():
    return Operator(make_embodiment("xarm7_leap_right"), DT, OperatorConfig())


def fresh(operator):
    home = operator.effectors["right"].ik.joints.home
    operator.reset(home, {"right": slice(0, 23)})
    operator.set_paused(False)
    operator._stream_paused = False
    operator._was_paused = False
    return home


def frame(T, t, side="right", **kw) -> HandFrame:
    return HandFrame(side=side, t_source=t, t_receive=t, joints=hand_joints(T, side), **kw)


def test_no_frames_means_holding_home(operator):
    home = fresh(operator)
    cmd = operator.command(0.0)["right"]
    assert cmd.hold and cmd.reason == "waiting"
    np.testing.assert_allclose(cmd.positions, home)


def test_first_frame_anchors_without_a_jump_then_the_robot_follows(operator):
    home = fresh(operator)
    op = operator.effectors["right"]
    T_robot0 = op.ik.T_world_hand()
    H0 = palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(H0, 0.0))
    cmd = operator.command(0.0)["right"]
    assert not cmd.hold
    np.testing.assert_allclose(cmd.positions[:7], home[:7], atol=1e-3)
    H = H0.copy()
    H[:3, 3] += [-0.05, 0.0, 0.04]
    t = 0.0
    for _ in range(90):
        t += DT
        operator.observe(frame(H, t))
        operator.command(t)
    moved = op.ik.T_world_hand()[:3, 3] - T_robot0[:3, 3]
    # The motion in the palm's initial frame, replayed in the robot hand's initial frame.
    expected = T_robot0[:3, :3] @ H0[:3, :3].T @ np.array([-0.05, 0.0, 0.04])
    np.testing.assert_allclose(moved, expected, atol=2e-3)


def test_tracking_loss_holds_after_the_timeout(operator, caplog):
    fresh(operator)
    H0 = palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(H0, 0.0))
    operator.command(0.0)
    with caplog.at_level(logging.WARNING, "beavr_sim.operator.operator"):
        cmd = operator.command(0.5)["right"]
    assert cmd.hold and cmd.reason == "tracking_lost"
    assert "lost" in caplog.text
    # An untracked hand (palm joints missing) does not count as tracking.
    joints = hand_joints(H0)
    joints[7] = np.nan
    operator.observe(HandFrame("right", 0.6, 0.6, joints))
    assert operator.command(0.6)["right"].reason == "tracking_lost"
    assert operator.effectors["right"].stats.untracked_frames == 1


def test_a_tracking_jump_is_ignored_then_reanchored_if_the_hand_stays(operator):
    fresh(operator)
    op = operator.effectors["right"]
    H0 = palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(H0, 0.0))
    q0 = operator.command(0.0)["right"].positions
    far = H0.copy()
    far[:3, 3] += [0.0, 0.0, 0.3]  # 30 cm in one frame: a glitch
    t = 0.0
    for _i in range(op.config.reanchor_after - 1):
        t += 1 / 60
        assert not op.observe(frame(far, t))
    np.testing.assert_allclose(operator.command(t)["right"].positions, q0, atol=1e-6)
    assert op.stats.jumps_rejected == op.config.reanchor_after - 1
    t += 1 / 60
    assert op.observe(frame(far, t))  # it stayed there: re-anchored, accepted
    reanchors = op.stats.reanchors
    cmd = operator.command(t)["right"]
    assert op.stats.reanchors == reanchors + 1
    np.testing.assert_allclose(cmd.positions[:7], q0[:7], atol=1e-3)  # no jump


def test_pause_holds_and_resume_reanchors_without_a_jump(operator):
    fresh(operator)
    H0 = palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(H0, 0.0))
    operator.command(0.0)
    H = H0.copy()
    t = 0.0
    for _ in range(10):  # paused by the stream while the hand moves 10 cm
        t += DT
        H[:3, 3] += [0.01, 0, 0]
        operator.observe(frame(H, t, paused=True))
        cmd = operator.command(t)["right"]
        assert cmd.hold and cmd.reason == "paused"
    q_paused = cmd.positions
    t += DT
    operator.observe(frame(H, t))
    cmd = operator.command(t)["right"]
    assert not cmd.hold
    np.testing.assert_allclose(cmd.positions[:7], q_paused[:7], atol=1e-3)


def test_left_hand_pinch_toggles_pause(operator):
    fresh(operator)
    L = palm_down([0.3, 0.2, 1.0])
    operator.observe(frame(L, 0.0, side="left", pinch=True))
    assert operator.paused
    operator.observe(frame(L, 0.1, side="left", pinch=True))  # held: no second toggle
    assert operator.paused
    operator.observe(frame(L, 0.2, side="left", pinch=False))
    operator.observe(frame(L, 0.3, side="left", pinch=True))
    assert not operator.paused
    assert operator.take_gestures() == []


def test_long_left_pinch_is_the_record_gesture_and_leaves_pause_as_it_was(operator):
    fresh(operator)
    L = palm_down([0.3, 0.2, 1.0])
    operator.observe(frame(L, -0.1, side="left", pinch=False))
    t = 0.0
    for _ in range(40):  # 1.3 s held
        operator.observe(frame(L, t, side="left", pinch=True))
        if t < 0.99:
            assert operator.paused  # the robot holds while the gesture is made
        t += 1 / 30
    assert not operator.paused
    assert operator.take_gestures() == ["record"]  # once per press
    assert operator.take_gestures() == []
    operator.observe(frame(L, t, side="left", pinch=False))
    assert not operator.paused and operator.take_gestures() == []


def test_both_hands_pinching_is_the_estop_gesture(operator):
    fresh(operator)
    L, R = palm_down([0.3, 0.2, 1.0]), palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(R, 0.0, pinch=True))  # one hand alone: no e-stop
    assert operator.take_gestures("estop") == []
    operator.observe(frame(L, 0.0, side="left", pinch=True))
    operator.observe(frame(L, 0.03, side="left", pinch=True))  # held: one gesture
    operator.observe(frame(R, 0.03, pinch=True))
    assert operator.take_gestures("estop") == ["estop"]
    operator.observe(frame(R, 0.06, pinch=False))
    operator.observe(frame(R, 0.1, pinch=True))  # pinched again: a second one
    gestures = operator.take_gestures("record")  # taking one kind leaves the other
    assert gestures == [] and operator.take_gestures() == ["estop"]
    with pytest.raises(UnknownNameError, match="estop"):
        operator.take_gestures("stop")


def test_gestures_nobody_takes_stay_bounded(operator):
    """A session that does not record never takes the record gesture: the queue keeps only
    the newest MAX_PENDING_GESTURES (it grew by one per gesture for the whole session)."""
    fresh(operator)
    L, R = palm_down([0.3, 0.2, 1.0]), palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(R, 0.0, pinch=True))
    t = 0.0
    for _ in range(100):  # both hands pinch again and again: one e-stop gesture each time
        operator.observe(frame(L, t, side="left", pinch=True))
        operator.observe(frame(L, t + 0.01, side="left", pinch=False))
        t += 0.02
    assert operator.take_gestures("record") == []
    assert operator.take_gestures() == ["estop"] * MAX_PENDING_GESTURES


def test_commands_respect_joint_limits(operator):
    fresh(operator)
    op = operator.effectors["right"]
    H0 = palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(H0, 0.0))
    t = 0.0
    for _ in range(60):  # ask for a pose far out of reach
        t += DT
        H = H0.copy()
        H[:3, 3] += [1.5, 0.0, -1.0]
        operator.observe(frame(H, t))
        cmd = operator.command(t)["right"]
        assert np.all(cmd.positions >= op.ik.joints.lower - 1e-9)
        assert np.all(cmd.positions <= op.ik.joints.upper + 1e-9)


def test_switching_resolution_reanchors_and_scales_motion_from_there(operator):
    fresh(operator)
    op = operator.effectors["right"]
    H0 = palm_down([0.3, -0.2, 1.0])
    operator.observe(frame(H0, 0.0))
    operator.command(0.0)
    H = H0.copy()
    H[:3, 3] += [0.0, 0.04, 0.0]  # sideways: clear of the table
    t = 0.0
    for _ in range(60):
        t += DT
        operator.observe(frame(H, t))
        operator.command(t)
    T_before = op.ik.T_world_hand()
    t += DT
    operator.observe(frame(H, t, resolution="low"))
    operator.command(t)
    np.testing.assert_allclose(op.ik.T_world_hand()[:3, 3], T_before[:3, 3], atol=1e-3)  # no jump
    H2 = H.copy()
    H2[:3, 3] += [0.0, 0.05, 0.0]
    for _ in range(60):
        t += DT
        operator.observe(frame(H2, t, resolution="low"))
        operator.command(t)
    moved = op.ik.T_world_hand()[:3, 3] - T_before[:3, 3]
    expected = 0.6 * (T_before[:3, :3] @ H0[:3, :3].T @ np.array([0.0, 0.05, 0.0]))
    np.testing.assert_allclose(moved, expected, atol=2e-3)
