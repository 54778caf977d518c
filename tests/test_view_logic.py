"""The browser view's logic without a browser: skeleton bones and segments, rate and latency
readouts, the update throttle, guard colours sent on transitions only, the control panel, and
the listener that drives the view from a teleop loop."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest

from beavr_sim.viz.twin_view import (
    BONES,
    WARNING_RGB,
    GuardTint,
    RateMeter,
    Throttle,
    ViewCost,
    recent_p50,
    skeleton_bones,
    skeleton_segments,
)
from beavr_sim.wire.hand import JOINT_INDEX, JOINT_NAMES


def test_skeleton_bones_follow_the_joint_names():
    bones = skeleton_bones()
    assert bones == BONES
    assert len(bones) == 1 + 4 + 4 * 5  # wrist-palm, thumb chain, four five-joint fingers
    children = [b for _, b in bones]
    # Every joint but the wrist is reached exactly once: a tree rooted at the wrist.
    assert sorted(children) == sorted(i for n, i in JOINT_INDEX.items() if n != "wrist")
    assert (JOINT_INDEX["wrist"], JOINT_INDEX["index_metacarpal"]) in bones
    assert (JOINT_INDEX["index_distal"], JOINT_INDEX["index_tip"]) in bones
    assert (JOINT_INDEX["thumb_distal"], JOINT_INDEX["thumb_tip"]) in bones


def test_skeleton_segments_from_keypoints_and_untracked_joints():
    rng = np.random.default_rng(0)
    kp = rng.normal(size=(len(JOINT_NAMES), 3))
    seg = skeleton_segments(kp)
    assert seg.shape == (len(BONES), 2, 3)
    for k, (a, b) in enumerate(BONES):
        np.testing.assert_allclose(seg[k, 0], kp[a], atol=1e-6)
        np.testing.assert_allclose(seg[k, 1], kp[b], atol=1e-6)
    # An untracked joint: its bones collapse onto the tracked end, nothing is NaN.
    kp[JOINT_INDEX["index_tip"]] = np.nan
    seg = skeleton_segments(kp)
    assert np.isfinite(seg).all() and seg.shape == (len(BONES), 2, 3)
    k = BONES.index((JOINT_INDEX["index_distal"], JOINT_INDEX["index_tip"]))
    np.testing.assert_allclose(seg[k, 0], seg[k, 1])
    np.testing.assert_allclose(seg[k, 0], kp[JOINT_INDEX["index_distal"]], atol=1e-6)
    assert np.isfinite(skeleton_segments(np.full((26, 3), np.nan))).all()
    with pytest.raises(ValueError, match="26 x 3"):
        skeleton_segments(np.zeros((21, 3)))


def test_rate_meter_measures_the_last_second():
    meter = RateMeter(1.0)
    assert meter.rate_hz() is None
    for k in range(90):  # 3 s at 30 Hz
        meter.tick(k / 30)
    assert meter.rate_hz() == pytest.approx(30.0)
    for k in range(1, 11):  # then 1 s at 10 Hz: the 30 Hz ticks drop out of the window
        meter.tick(89 / 30 + k / 10)
    assert meter.rate_hz() == pytest.approx(10.0, rel=0.05)


def test_recent_p50():
    assert recent_p50([]) is None
    assert recent_p50([5.0, 1.0, 3.0]) == 3.0
    assert recent_p50([100.0] * 10 + [1.0] * 200) == 1.0  # only the last 200


def test_throttle_limits_updates_without_skipping_periods():
    throttle = Throttle(30.0)
    due = sum(throttle.due(k / 100) for k in range(100))  # 1 s of calls at 100 Hz
    assert 29 <= due <= 31
    # Calls exactly at 30 Hz, each a little early or late: every one is due.
    throttle = Throttle(30.0)
    jitter = np.random.default_rng(1).uniform(-2e-3, 2e-3, 60)
    assert all(throttle.due(k / 30 + j) for k, j in enumerate(jitter))
    # After a stall it does not fire twice in a row.
    assert throttle.due(10.0) and not throttle.due(10.001)
    assert all(Throttle(0.0).due(t) for t in np.zeros(5))


class _Handle:
    def __init__(self, color):
        self._color = color
        self.sent = 0

    @property
    def color(self):
        return self._color

    @color.setter
    def color(self, value):
        self._color = value
        self.sent += 1


def test_guard_tint_sends_colours_on_transitions_only():
    right = [_Handle((10, 10, 10)), _Handle((200, 200, 200))]
    left = [_Handle((50, 50, 50))]
    tint = GuardTint({"right": [(h, h.color) for h in right], "left": [(h, h.color) for h in left]})
    assert tint.show([]) == 0
    assert tint.show(["right"]) == 2
    assert [h.color for h in right] == [WARNING_RGB] * 2 and left[0].color == (50, 50, 50)
    assert tint.show(["right"]) == 0  # still blocked: nothing sent
    assert tint.show(["right", "left", "unknown"]) == 1
    assert tint.show(["left"]) == 2  # right clears: its own colours back
    assert [h.color for h in right] == [(10, 10, 10), (200, 200, 200)]
    assert tint.show([]) == 1 and left[0].color == (50, 50, 50)
    assert sum(h.sent for h in right + left) == 6


# ---------------------------------------------------------------------------- with viser
viser = pytest.importorskip("viser", reason="viser (extra 'viz') not installed")


def test_view_cost_per_tick_and_share_of_the_period():
    cpu = iter([1.0, 1.003])  # the server thread's CPU clock: 3 ms in 0.5 s
    cost = ViewCost(1.0, server_cpu=lambda: next(cpu))
    for k in range(30):  # 30 ticks in 0.5 s, 1 ms each in the loop's thread
        cost.add(0.001, now=10.0 + k / 60)
    cost.sample_server(now=10.0)
    cost.sample_server(now=10.5)
    busy, server = cost.per_second(now=10.5)
    assert busy == pytest.approx(0.030) and server == pytest.approx(0.006)
    text = cost.readout(60.0, clients=1, now=10.5)
    # (30 + 6) ms per second at 60 ticks per second: 0.6 ms per tick, 3.6 % of the time.
    assert text == "view **0.60 ms/tick** (loop 0.50, sending 0.10; 3.6 % of the time) · 1 browser"
    assert ViewCost().readout(None, clients=2) == "view - ms/tick · 2 browsers"
    unreadable = ViewCost(server_cpu=None)
    unreadable.sample_server()
    assert unreadable.per_second()[1] is None


@pytest.fixture()
def loop():
    from beavr_sim.teleop.session import SessionOptions, build_loop

    options = SessionOptions(
        task="pick_place",
        source="trace",
        viser=False,
        clock="virtual",
        headless=True,
        progress=False,
    )
    loop = build_loop(options)
    yield loop
    loop.twin.env.close()


def test_view_panel_overlays_and_guard_colours(loop):
    from beavr_sim.teleop.view import attach_view

    view = attach_view(loop, "127.0.0.1", 0, rate_hz=0.0)
    try:
        assert view.host == "127.0.0.1" and view.estop_button is None  # no hardware: no E-stop
        assert "PickPlace" in view.info.content and "xarm7_leap_right" in view.info.content
        listener = loop.listeners[-1]
        for _ in range(60):
            tick = loop.tick()
        assert view.updates == 60  # rate_hz=0: every tick
        overlay = view.overlays["right"]
        targets = loop.operator.targets()["right"]
        assert overlay.bones.visible and overlay.joints.visible and overlay.tips.visible
        assert overlay.frame.visible
        np.testing.assert_allclose(overlay.frame.position, targets.T_world_target[:3, 3])
        np.testing.assert_allclose(overlay.bones.points, skeleton_segments(targets.keypoints_world))
        assert "loop rate" in view.readout.content and "Hz" in view.readout.content
        # What the view costs the loop, per tick and as a share of the wall time; no browser.
        assert "view **" in view.readout.content and " ms/tick**" in view.readout.content
        assert "% of the time" in view.readout.content
        assert "0 browsers" in view.readout.content
        busy, _ = view.cost.per_second()
        assert busy > 0

        # Guard: the right effector's geoms turn red on the block, back when it clears.
        right = view.guard.geoms["right"]
        assert right and all(h.color == own for h, own in right)
        assert len(view.geom_handles) > len(right)  # the table and objects are not tinted
        blocked = dataclasses.replace(
            tick,
            state=dataclasses.replace(
                tick.state, guard_blocked=True, guard_blocked_effectors=("right",)
            ),
        )
        listener(blocked)
        assert all(tuple(h.color) == WARNING_RGB for h, _ in right)
        assert view.guard_badge.visible and "right" in view.guard_badge.content
        listener(tick)
        assert all(tuple(h.color) == tuple(own) for h, own in right)
        assert not view.guard_badge.visible

        # Success: badge on; a new episode (time goes back) clears it.
        won = dataclasses.replace(tick, state=dataclasses.replace(tick.state, success=True))
        listener(won)
        assert view.success_badge.visible and "success" in view.status.content
        loop.reset(loop.seed)
        listener(loop.tick())
        assert not view.success_badge.visible

        # Pause and reset from the panel act at the next tick.
        view._toggle_pause()
        assert view.pause_button.label == "Resume"
        loop.tick()
        assert loop.operator.paused and "paused" in view.status.content
        view._toggle_pause()
        loop.tick()
        assert not loop.operator.paused and view.pause_button.label == "Pause"
        view.reset_requested = True
        loop.tick()
        assert listener.resets == 1 and loop.ticks == 0 and not loop.source.finished
    finally:
        view.close()


def test_view_is_rate_limited_and_estop_only_when_mirroring(loop, monkeypatch):
    from beavr_sim.teleop import view as view_module
    from beavr_sim.teleop.episodes import EpisodeControl
    from beavr_sim.teleop.view import attach_view, episode_line

    control = EpisodeControl()
    view = attach_view(loop, "127.0.0.1", 0, control=control, mirroring=True, rate_hz=5.0)
    wall = [100.0]  # the listener's wall clock, moved by hand (a loaded machine's ticks are slow)
    monkeypatch.setattr(view_module, "time", types.SimpleNamespace(perf_counter=lambda: wall[0]))
    try:
        for _ in range(30):  # 30 ticks in 0.29 s of wall time: 5 Hz allows 2 updates
            loop.tick()
            wall[0] += 0.01
        assert view.updates == 2
        assert view.estop_button is not None
        view._estop()
        loop.tick()
        assert view.estop_requested and loop.operator.paused
        assert view.episode is not None
    finally:
        view.close()
    assert episode_line("episode 2/5: REC") == "episode **2** of **5** · **recording**"
    assert episode_line("episode 1/3: idle (start: Enter)") == "episode **1** of **3** · idle"
    assert episode_line("") == "idle"


def test_view_access_lets_anyone_stop_but_only_token_holders_move():
    from beavr_sim.viz.view_access import ViewAccess
    from beavr_sim.wire.access import SessionToken

    access = ViewAccess(SessionToken("view-T0ken", True))
    for action in ("estop", "pause"):
        assert access.permits(action, 1)
    for action in ("resume", "reset", "record", "discard", "release"):
        assert not access.permits(action, 1)
    assert sum(access.refused.values()) == 5
    assert not access.enter(1, "view-T0kem") and not access.permits("reset", 1)
    assert access.enter(1, "view-T0ken") and access.permits("reset", 1)
    assert not access.permits("release", 2)  # another client did not enter it
    access.forget(1)
    assert not access.permits("record", 1)
    assert ViewAccess(SessionToken("x", False)).permits("release", None)  # loopback: open
    with pytest.raises(ValueError, match="estop"):
        access.permits("resett", 1)


def test_view_buttons_need_the_token_except_stop_and_pause(loop):
    from types import SimpleNamespace

    from beavr_sim.teleop.view import attach_view
    from beavr_sim.wire.access import SessionToken

    def press(button, client_id: int) -> None:  # as viser calls a click handler
        for callback in button._impl.update_cb:
            callback(SimpleNamespace(client=None, client_id=client_id, target=button))

    token = SessionToken("view-T0ken", True)
    view = attach_view(loop, "127.0.0.1", 0, mirroring=True, token=token)
    try:
        press(view.estop_button, 7)  # anyone may stop
        press(view.pause_button, 7)
        assert view.estop_requested and view.paused
        press(view.estop_button, 7)  # release, resume, reset: refused without the token
        press(view.pause_button, 7)
        press(view.reset_button, 7)
        assert view.estop_requested and view.paused and not view.take_reset()
        assert view.refused == 3 and "refused" in view.access_note.content
        view.access.enter(7, "view-T0ken")
        press(view.estop_button, 7)
        press(view.pause_button, 7)
        press(view.reset_button, 7)
        assert not view.estop_requested and not view.paused and view.take_reset()
    finally:
        view.close()
