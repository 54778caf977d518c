"""The operator's per-frame and per-tick path never raises and never holds silently.

Untracked joints, malformed frames, exceptions inside the tick and infeasible QPs become
counted hold reasons (``OperatorStats.holds``); the smoothing delay is set in seconds, the
same at any frame rate; and under random frame streams no command moves a joint faster than
its limit allows.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from beavr_sim.operator.operator import HOLD_REASONS, Operator, OperatorConfig
from beavr_sim.operator.retarget import human_keypoints_for, human_template
from beavr_sim.robots import make_embodiment
from beavr_sim.wire.hand import JOINT_INDEX, N_JOINTS, HandFrame

DT = 1 / 30
LOGGER = "beavr_sim.operator.operator"
INDEX_MOTORS = slice(7, 11)  # arm (7) then LEAP motor ids 0-3: the index finger
MIDDLE_MOTORS = slice(11, 15)


def palm_down(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]])
    T[:3, 3] = p
    return T


def hand_joints(T: np.ndarray, side: str = "right", q_hand=None) -> np.ndarray:
    kp = human_keypoints_for(np.zeros(16) if q_hand is None else q_hand, side)
    return kp @ T[:3, :3].T + T[:3, 3]


def malformed(frame: HandFrame, **fields) -> HandFrame:
    """``frame`` with fields its constructor would refuse (a buggy or hostile source)."""
    for name, value in fields.items():
        object.__setattr__(frame, name, value)
    return frame


@pytest.fixture(scope="module")
def operator() -> Operator:
    return Operator(make_embodiment("xarm7_leap_right"), DT, OperatorConfig())


@pytest.fixture(scope="module")
def bimanual() -> Operator:
    return Operator(make_embodiment("xarm7_leap_bimanual"), DT, OperatorConfig())


def fresh(operator: Operator) -> dict[str, np.ndarray]:
    """Re-home every effector; returns the home command per effector."""
    slices, homes, start = {}, {}, 0
    for name, op in operator.effectors.items():
        n = len(op.ik.joints.home)
        slices[name], homes[name] = slice(start, start + n), op.ik.joints.home.copy()
        start += n
    operator.reset(np.concatenate(list(homes.values())), slices)
    operator.set_paused(False)
    operator._stream_paused = False
    operator._was_paused = False
    operator._last_pinch = {"right": False, "left": False}
    operator.take_gestures()
    for op in operator.effectors.values():
        op.stats = type(op.stats)()
    return homes


# ------------------------------------------------------------------ untracked joints (item 1)
FLEX = np.array([0.0, 0.9, 0.7, 0.5] * 3 + [0.3, 0.2, 0.0, 0.2])  # a loose fist


def _finger_stream(
    operator: Operator, dropout: range, untracked_at: str = "nan"
) -> list[np.ndarray]:
    """72 Hz frames: a still open hand, then closing over 60 frames, then held closed; the
    index tip untracked in the frames of ``dropout``: NaN (as the Quest parser gives it), or
    flagged untracked at finite coordinates (``"origin"``: the Quest app's raw ``0,0,0``, as
    any source may pass it on; only the flag says it is not tracked)."""
    fresh(operator)
    H = palm_down([0.3, -0.2, 1.0])
    commands = []
    tip = JOINT_INDEX["index_tip"]
    for k in range(140):
        t = k / 72
        s = min(max((k - 20) / 60, 0.0), 1.0)
        joints = hand_joints(H, q_hand=s * FLEX)
        tracked = np.ones(N_JOINTS, dtype=bool)
        if k in dropout:
            tracked[tip] = False
            joints[tip] = np.nan if untracked_at == "nan" else 0.0
        operator.observe(HandFrame("right", t, t, joints, tracked))
        cmd = operator.command(t)["right"]
        assert not cmd.hold, (k, cmd.reason)
        commands.append(cmd.positions)
    return commands


@pytest.mark.parametrize("untracked_at", ["nan", "origin"])
def test_an_untracked_fingertip_holds_that_finger_and_it_resumes(operator, untracked_at):
    dropout = range(40, 46)  # six frames, mid-motion
    commands = _finger_stream(operator, dropout, untracked_at)
    held = np.array([c[INDEX_MOTORS] for c in commands[dropout.start : dropout.stop]])
    # The index finger does not move while its tip is untracked (wherever the untracked
    # joint's coordinates say it is).
    moved = np.abs(held - commands[dropout.start - 1][INDEX_MOTORS]).max()
    assert moved == 0.0, f"the index finger moved {moved:.3f} rad on an untracked tip"
    middle = np.array([c[MIDDLE_MOTORS] for c in commands[dropout.start - 1 : dropout.stop]])
    assert np.ptp(middle, axis=0).max() > 0.05  # the other fingers kept moving
    after = commands[dropout.stop + 2][INDEX_MOTORS] - commands[dropout.stop - 1][INDEX_MOTORS]
    assert np.abs(after).max() > 0.01  # the index resumes
    reference = _finger_stream(operator, range(0))
    np.testing.assert_allclose(commands[-1][7:], reference[-1][7:], atol=0.02)
    assert operator.effectors["right"].stats.untracked_frames == 0  # the palm stayed tracked


# ------------------------------------------------------------------ never raise (item 2)
def _drive(operator: Operator, t0: float, n: int, side: str = "right"):
    H = palm_down([0.3, -0.2 if side == "right" else 0.2, 1.0])
    cmd = None
    for k in range(n):
        t = t0 + k * DT
        operator.observe(HandFrame(side, t, t, hand_joints(H, side)))
        cmd = operator.command(t)
    return cmd


def test_an_exception_in_the_tick_is_a_counted_error_hold(operator, monkeypatch, caplog):
    fresh(operator)
    op = operator.effectors["right"]
    last = _drive(operator, 0.0, 3)["right"]

    def broken(*_args, **_kwargs):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(op.ik, "step", broken)
    with caplog.at_level(logging.WARNING, LOGGER):
        for k in range(12):
            cmd = _drive(operator, 0.1 + k * DT, 1)["right"]
            assert cmd.hold and cmd.reason == "error"
            np.testing.assert_array_equal(cmd.positions, last.positions)
    assert op.stats.holds["error"] == 12 and op.stats.errors == 12
    logged = [r for r in caplog.records if "solver exploded" in r.getMessage()]
    assert len(logged) == 2  # the 1st and the 10th
    monkeypatch.undo()
    cmd = _drive(operator, 1.0, 1)["right"]
    assert not cmd.hold
    assert np.abs(cmd.positions - last.positions).max() <= op.ik.config.max_joint_speed * DT + 1e-6


def test_an_exception_in_the_retargeting_is_a_counted_error_hold(operator, monkeypatch):
    fresh(operator)
    op = operator.effectors["right"]
    last = _drive(operator, 0.0, 3)["right"]
    monkeypatch.setattr(op.retargeter, "retarget", lambda *a: 1 / 0)
    cmd = _drive(operator, 0.2, 1)["right"]
    assert cmd.hold and cmd.reason == "error"
    np.testing.assert_array_equal(cmd.positions, last.positions)
    assert op.stats.holds == {"error": 1}


def test_malformed_frames_never_raise(operator, caplog):
    fresh(operator)
    op = operator.effectors["right"]
    _drive(operator, 0.0, 3)
    H = palm_down([0.3, -0.2, 1.0])
    good = hand_joints(H)
    nan_palm = good.copy()
    nan_palm[JOINT_INDEX["wrist"]] = np.nan
    bad = [
        malformed(HandFrame("right", 0.2, 0.2, good), joints=good[:25]),
        malformed(HandFrame("right", 0.2, 0.2, good), joints=np.zeros((26, 2))),
        malformed(HandFrame("right", 0.2, 0.2, good), tracked=np.ones(3, dtype=bool)),
        malformed(HandFrame("right", 0.2, 0.2, good), joints=nan_palm),  # NaN, flagged tracked
        malformed(HandFrame("right", 0.2, 0.2, good), t_source=float("nan")),
        malformed(HandFrame("right", 0.2, 0.2, good), t_receive=float("inf")),
        malformed(HandFrame("right", 0.2, 0.2, good), side="up"),
        malformed(HandFrame("right", 0.2, 0.2, good), joints="garbage"),
        malformed(HandFrame("right", 0.2, 0.2, np.zeros((26, 3)))),  # degenerate palm
        None,
    ]
    with caplog.at_level(logging.WARNING, LOGGER):
        for frame in bad:
            operator.observe(frame)  # type: ignore[arg-type]
            cmd = operator.command(0.2)["right"]
            assert np.isfinite(cmd.positions).all()
    assert op._T_palm is not None and np.isfinite(op._T_palm).all()
    cmd = _drive(operator, 0.3, 1)["right"]  # a good frame afterwards is used
    assert not cmd.hold and np.isfinite(cmd.positions).all()
    assert caplog.records  # each kind was reported


# ------------------------------------------------------------------ silent holds (item 6)
def test_an_infeasible_arm_ik_step_is_a_counted_hold(operator, monkeypatch, caplog):
    fresh(operator)
    op = operator.effectors["right"]
    last = _drive(operator, 0.0, 3)["right"]
    monkeypatch.setattr(op.ik._qp, "solve", lambda A, h: None)
    H = palm_down([0.3, -0.2, 1.0])
    with caplog.at_level(logging.WARNING, LOGGER):
        for k in range(10):
            t = 0.1 + k * DT
            q = (k + 1) / 10 * FLEX
            operator.observe(HandFrame("right", t, t, hand_joints(H, q_hand=q)))
            cmd = operator.command(t)["right"]
            assert cmd.hold and cmd.reason == "ik_infeasible"
            np.testing.assert_array_equal(cmd.positions[:7], last.positions[:7])  # arm held
    assert np.abs(cmd.positions[7:] - last.positions[7:]).max() > 0.05  # fingers followed
    assert op.stats.holds == {"ik_infeasible": 10}
    assert len([r for r in caplog.records if "infeasible" in r.getMessage()]) == 2


def test_the_arm_ik_reports_a_step_without_a_solution(operator, monkeypatch):
    ik = operator.effectors["right"].ik
    fresh(operator)
    target = ik.T_world_hand()
    target[:3, 3] += [0.0, 0.05, 0.0]
    q0 = ik.step(target)
    assert not ik.infeasible
    before = ik.infeasible_iterations
    monkeypatch.setattr(ik._qp, "solve", lambda A, h: None)
    np.testing.assert_array_equal(ik.step(target), q0)
    assert ik.infeasible and ik.infeasible_iterations == before + ik.config.iterations
    monkeypatch.undo()
    assert np.abs(ik.step(target) - q0).max() > 0 and not ik.infeasible


def test_an_infeasible_retargeting_step_holds_the_fingers_and_is_counted(operator, monkeypatch):
    fresh(operator)
    op = operator.effectors["right"]
    last = _drive(operator, 0.0, 3)["right"]
    monkeypatch.setattr(op.retargeter._qp, "solve", lambda A, h: None)
    H = palm_down([0.3, -0.18, 1.0])  # the arm has somewhere to go
    for k in range(5):
        t = 0.1 + k * DT
        operator.observe(HandFrame("right", t, t, hand_joints(H, q_hand=FLEX)))
        cmd = operator.command(t)["right"]
        assert cmd.reason == "retarget_infeasible"
        np.testing.assert_array_equal(cmd.positions[7:], last.positions[7:])  # fingers held
    assert op.stats.holds == {"retarget_infeasible": 5}
    assert set(op.stats.holds) <= set(HOLD_REASONS)


def test_every_held_tick_is_counted_by_reason(operator):
    fresh(operator)
    op = operator.effectors["right"]
    operator.command(0.0)  # no frame yet
    _drive(operator, 0.0, 2)
    operator.set_paused(True)
    operator.command(0.1)
    operator.command(0.13)
    operator.set_paused(False)
    operator.command(0.5)  # no frame for 0.45 s
    assert op.stats.holds == {"waiting": 1, "paused": 2, "tracking_lost": 1}
    assert set(op.stats.holds) <= set(HOLD_REASONS)


def test_the_end_of_the_source_is_its_own_hold_not_a_tracking_loss(operator, caplog):
    """A trace that ends is not a lost hand: ``source_ended`` holds, counted under that name,
    no tracking loss and no warning (an INFO line); the held command does not move."""
    fresh(operator)
    op = operator.effectors["right"]
    last = _drive(operator, 0.0, 3)["right"]
    operator.set_source_ended(True)  # the runner: no frame will come again
    with caplog.at_level(logging.INFO, logger=LOGGER):
        for t in (0.2, 0.4, 0.5, 0.9):
            cmd = operator.command(t)["right"]
    assert cmd.hold and cmd.reason == "source_ended"
    np.testing.assert_array_equal(cmd.positions, operator.command(1.0)["right"].positions)
    assert np.abs(cmd.positions - last.positions).max() < 0.05  # held where it was
    assert op.stats.holds == {"source_ended": 4}
    assert op.stats.tracking_losses == 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    ended = [r for r in caplog.records if "source ended" in r.getMessage()]
    assert len(ended) == 1 and ended[0].levelno == logging.INFO  # said once
    assert set(op.stats.holds) <= set(HOLD_REASONS)


def test_a_hand_lost_before_the_source_ended_stays_lost_and_a_replay_loses_it_again(operator):
    fresh(operator)
    op = operator.effectors["right"]
    _drive(operator, 0.0, 3)
    assert operator.command(0.5)["right"].reason == "tracking_lost"  # lost mid-trace
    operator.set_source_ended(True)
    assert operator.command(0.6)["right"].reason == "tracking_lost"
    operator.set_source_ended(False)  # replayed from its start: a live stream again
    _drive(operator, 1.0, 2)
    assert operator.command(1.5)["right"].reason == "tracking_lost"
    assert op.stats.tracking_losses == 2
    assert "source_ended" not in op.stats.holds


# ------------------------------------------------------------------ time-based filters (item 8)
def _palm_lag(operator: Operator, rate_hz: float, speed: float = 0.1) -> float:
    """Seconds by which the arm target trails a hand moving at ``speed`` (m/s), with frames
    at ``rate_hz``: still for 0.5 s, then a ramp for 1 s; measured from the target's
    position at two instants of the ramp's steady state (the map's scale drops out)."""
    fresh(operator)
    op = operator.effectors["right"]
    p0, direction = np.array([0.3, -0.2, 1.0]), np.array([0.6, 0.0, 0.8])
    samples = []
    for k in range(int(1.5 * rate_hz) + 1):
        t = k / rate_hz
        p = p0 + direction * speed * max(t - 0.5, 0.0)
        operator.observe(HandFrame("right", t, t, hand_joints(palm_down(p))))
        operator.command(t)
        samples.append((t, op.targets().T_world_target[:3, 3]))
    start = samples[int(0.5 * rate_hz) - 1][1]
    (t1, p1), (t2, p2) = samples[int(1.25 * rate_hz)], samples[-1]
    d1, d2 = np.linalg.norm(p1 - start), np.linalg.norm(p2 - start)
    slope = (d2 - d1) / (t2 - t1)  # scale x speed
    return (t2 - 0.5) - d2 / slope


def test_the_smoothing_delay_is_the_same_at_any_frame_rate(operator):
    lags = {rate: _palm_lag(operator, rate) for rate in (30.0, 60.0, 90.0)}
    assert max(lags.values()) - min(lags.values()) < 0.003, lags
    assert 0.03 < lags[60.0] < 0.05, lags  # about the former filters' 44 ms at 60 Hz


def test_out_of_order_and_repeated_stamps_keep_the_filters_finite(operator):
    fresh(operator)
    H = palm_down([0.3, -0.2, 1.0])
    for t in (0.0, 0.03, 0.03, 0.02, -5.0, 0.06, 0.06, 0.09):
        H[:3, 3] += [0.001, 0.0, 0.0]
        operator.observe(HandFrame("right", t, 0.1, hand_joints(H)))
        cmd = operator.command(0.1)["right"]
        assert np.isfinite(cmd.positions).all() and not cmd.hold
    op = operator.effectors["right"]
    assert np.isfinite(op._T_palm).all()


# ------------------------------------------------------------------ property test
@st.composite
def frame_events(draw, sides: tuple[str, ...]):
    """One step of a random stream: a frame (or a malformed one) and whether a tick follows."""
    side = draw(st.sampled_from(sides))
    kind = draw(
        st.sampled_from(["normal"] * 6 + ["jump", "palm_untracked", "nan", "malformed", "none"])
    )
    return {
        "side": side,
        "kind": kind,
        "dt": draw(st.sampled_from([1 / 90, 1 / 72, 1 / 30, 0.0, -0.02, 0.4])),
        "move": draw(st.lists(st.floats(-0.02, 0.02), min_size=3, max_size=3)),
        "fingers": draw(st.floats(0.0, 1.0)),
        "untracked": draw(st.lists(st.integers(0, N_JOINTS - 1), max_size=4)),
        "pinch": draw(st.booleans()) and draw(st.booleans()),
        "paused": draw(st.integers(0, 9)) == 0,
        "resolution": draw(st.sampled_from(["high"] * 4 + ["low"])),
        "tick": draw(st.integers(0, 3)) > 0,
    }


def _event_frame(event: dict, t: float, H: np.ndarray) -> HandFrame | None:
    side, kind = event["side"], event["kind"]
    joints = human_template(side) * 1.0
    joints[2:] *= 1.0 - 0.3 * event["fingers"]  # curl-ish: pull the fingers in
    joints = joints @ H[:3, :3].T + H[:3, 3]
    if kind == "jump":
        joints += [0.0, 0.0, 0.4]
    tracked = np.ones(N_JOINTS, dtype=bool)
    tracked[event["untracked"]] = False
    if kind == "palm_untracked":
        tracked[JOINT_INDEX["wrist"]] = False
    joints[~tracked] = np.nan
    frame = HandFrame(side, t, t, joints, tracked, pinch=event["pinch"], paused=event["paused"],
                      resolution=event["resolution"])  # fmt: skip
    if kind == "nan":  # NaN in joints flagged tracked
        bad = joints.copy()
        bad[JOINT_INDEX["index_tip"]] = np.nan
        bad[JOINT_INDEX["middle_proximal"]] = np.inf
        return malformed(frame, joints=bad, tracked=np.ones(N_JOINTS, dtype=bool))
    if kind == "malformed":
        return malformed(frame, joints=joints[:20])
    if kind == "none":
        return None
    return frame


def _check_stream(operator: Operator, events: list[dict]) -> None:
    previous = fresh(operator)
    limits = {
        name: np.concatenate(
            [
                np.full(op.n_arm, op.ik.config.max_joint_speed * op.ik.dt),
                np.full(
                    len(previous[name]) - op.n_arm,
                    op.retargeter.config.max_step * op.retargeter.config.iterations,
                ),
            ]
        )
        + 1e-6
        for name, op in operator.effectors.items()
    }
    H = {s: palm_down([0.3, -0.2 if s == "right" else 0.2, 1.0]) for s in ("right", "left")}
    t = now = 0.0
    for event in events:
        t += event["dt"]
        H[event["side"]][:3, 3] += event["move"]
        operator.observe(_event_frame(event, t, H[event["side"]]))  # type: ignore[arg-type]
        if not event["tick"]:
            continue
        now += DT
        commands = operator.command(now)
        for name, cmd in commands.items():
            op = operator.effectors[name]
            assert cmd.reason in HOLD_REASONS
            assert np.isfinite(cmd.positions).all()
            assert np.all(cmd.positions >= op.ik.joints.lower - 1e-9)
            assert np.all(cmd.positions <= op.ik.joints.upper + 1e-9)
            step = np.abs(cmd.positions - previous[name])
            assert np.all(step <= limits[name]), (name, cmd.reason, step - limits[name])
            previous[name] = cmd.positions
    for op in operator.effectors.values():
        assert op.stats.errors == 0, op.stats


_settings = settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@_settings
@given(events=st.lists(frame_events(("right",)), min_size=1, max_size=40))
def test_random_streams_never_raise_or_outrun_the_joint_speed_limits(operator, events):
    _check_stream(operator, events)


@_settings
@given(events=st.lists(frame_events(("right", "left")), min_size=1, max_size=40))
def test_random_bimanual_streams_never_raise_or_outrun_the_joint_speed_limits(bimanual, events):
    _check_stream(bimanual, events)
