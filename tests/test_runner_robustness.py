"""The teleop runners keep running: no catch-up bursts after a stall, listeners that raise or
are slow never stop or slow the control tick, an operator error is a hold (never an exit), a
reset in ``--multiprocess`` re-homes to the new pose, and the summary says why each effector
held. Issue 25 (items 4, 5, 7, 8 and the runner half of item 1)."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

import numpy as np
import pytest
import zmq
from waiting import HANG_GUARD_S, wait_until

from beavr_sim.assets import bundled_trace
from beavr_sim.teleop.session import SessionOptions, build_loop
from beavr_sim.traces.format import TraceReader
from beavr_sim.wire.ports import PortConfig, TransportConfig

#: LEAP hand motors of the index finger (after the arm's 7 joints on the xArm7).
INDEX = slice(7, 11)


def trace_loop(clock: str = "virtual", task: str = "PickupBox"):
    options = SessionOptions(
        task=task, source="trace", viser=False, headless=True, progress=False, clock=clock
    )
    return build_loop(options)


class WallStamps:
    """A tick listener that notes the wall time of every tick and stalls once (a slow disk, a
    GC pause, a render that hung) after tick ``stall_after``."""

    def __init__(self, stall_after: int | None = None, stall_s: float = 0.3):
        self.times: list[float] = []
        self.stall_after = stall_after
        self.stall_s = stall_s

    def __call__(self, tick) -> None:
        self.times.append(time.monotonic())
        if len(self.times) == self.stall_after:
            time.sleep(self.stall_s)


class TickStarts:
    """Records the schedule's tick starts (on its grid, so how the machine kept up does not
    matter) and the overruns counted by then; wraps ``loop.schedule.wait``."""

    def __init__(self, loop) -> None:
        self.starts: list[float] = []
        self.overruns: list[int] = []
        schedule, wait = loop.schedule, loop.schedule.wait

        def recorded(*args, **kwargs) -> float:
            start = wait(*args, **kwargs)
            self.starts.append(start)
            self.overruns.append(schedule.overruns)
            return start

        schedule.wait = recorded


# ------------------------------------------------------------------ item 4: no bursts
def test_a_stall_does_not_cause_a_burst_of_ticks_and_the_replay_stays_the_same():
    loop = trace_loop("paced")
    stamps = WallStamps(stall_after=10)
    loop.listeners.append(stamps)
    starts = TickStarts(loop)
    try:
        summary = loop.run(max_seconds=1.2)
        q_paced = loop.twin.env.data.qpos.copy()
    finally:
        loop.twin.env.close()
    intervals = np.diff(stamps.times)
    assert intervals[9] >= 0.3  # the stall
    # Without a guard the ~9 missed deadlines run back to back (a few ms apart): every tick
    # starts at least a period after the one before, the late one after the stall included.
    after = np.diff(starts.starts)[10:]
    assert after.min() >= loop.dt - 1e-9, f"burst after the stall: {np.round(after * 1e3, 1)} ms"
    assert summary.overruns >= 1 and summary.missed_ticks >= 6, summary
    # Skipped wall deadlines keep the virtual time per tick: the same episode as unpaced.
    virtual = trace_loop("virtual")
    try:
        plain = virtual.run(max_seconds=1.2)
        np.testing.assert_array_equal(virtual.twin.env.data.qpos, q_paced)
    finally:
        virtual.twin.env.close()
    assert (plain.ticks, plain.commands_applied, plain.holds) == (
        summary.ticks,
        summary.commands_applied,
        summary.holds,
    )


def test_the_paced_clock_starts_when_the_loop_runs_not_at_reset():
    loop = trace_loop("paced")  # reset happened in build_loop
    time.sleep(0.3)  # slow set-up (a view, a rerun log) between reset and run
    starts = TickStarts(loop)
    try:
        loop.run(max_seconds=0.5)
    finally:
        loop.twin.env.close()
    # The first tick is on time (the set-up is no overrun) and no tick catches up on it.
    assert starts.overruns[0] == 0, "the set-up between reset and run counted as an overrun"
    first = np.diff(starts.starts)[:8]
    assert first.min() >= loop.dt - 1e-9, f"burst at start: {np.round(first * 1e3, 1)} ms"


# ------------------------------------------------------------------ item 5: listeners
def test_a_raising_listener_is_counted_and_does_not_stop_the_loop(caplog):
    loop = trace_loop()
    after = WallStamps()

    def broken_view(tick):
        raise RuntimeError("listener bug")

    loop.listeners += [broken_view, after]
    try:
        with caplog.at_level(logging.WARNING, logger="beavr_sim.teleop.pipeline"):
            summary = loop.run(max_seconds=1.0)
    finally:
        loop.twin.env.close()
    assert summary.ticks == 30 and len(after.times) == 30  # later listeners still ran
    assert summary.listener_errors == {"broken_view": 30}
    logged = [r for r in caplog.records if "broken_view" in r.getMessage()]
    assert 1 <= len(logged) <= 3, "listener errors are logged, rate-limited"


def test_a_slow_threaded_listener_stays_off_the_control_tick():
    from beavr_sim.teleop.pipeline import ThreadedListener

    seen: list[float] = []
    threads: set[int] = set()
    release = threading.Event()  # the render is stuck until the ten ticks are done
    stuck: list[float] = []

    def slow_render(t: float) -> None:
        threads.add(threading.get_ident())
        if not stuck and not release.wait(HANG_GUARD_S):
            stuck.append(t)  # the ticks waited for the render: it never got released
        seen.append(t)

    def failing(t: float) -> None:
        raise ValueError("no GL")

    loop = trace_loop()
    slow = ThreadedListener(slow_render, snapshot=lambda tick: tick.t)
    bad = ThreadedListener(failing, snapshot=lambda tick: tick.t, name="bad_render")
    loop.listeners += [slow, bad]
    try:
        for _ in range(10):
            loop.tick()
        release.set()
        wait_until(
            lambda: slow.handled + slow.dropped == 10 and bad.errors + bad.dropped == 10,
            "the threaded listeners took the last tick",
        )
        summary = loop.summary(False)
    finally:
        release.set()
        slow.close()
        bad.close()
        loop.twin.env.close()
    assert not stuck, "the ticks waited for the render: it ran in (or blocked) the tick"
    assert threads and threading.get_ident() not in threads
    assert 1 <= len(seen) < 10 and slow.dropped > 0  # drop-oldest: the newest is rendered
    assert seen == sorted(seen)
    assert summary.listener_errors.get("bad_render", 0) >= 1
    assert not slow.alive and not bad.alive


def test_the_headset_image_is_rendered_off_the_control_thread_from_a_copy():
    from beavr_sim.teleop.session import headset_listener

    class Publisher:
        def __init__(self):
            self.images: list[np.ndarray] = []
            self.threads: set[int] = set()

        def publish(self, image: np.ndarray) -> bool:
            self.threads.add(threading.get_ident())
            self.images.append(image)
            return True

    loop = trace_loop()
    publisher = Publisher()
    listener = headset_listener(publisher, loop, (160, 90), period_s=0.0)
    loop.listeners.append(listener)
    try:
        for _ in range(5):
            loop.tick()
        deadline = time.monotonic() + 30
        while not publisher.images and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        listener.close()
        loop.twin.env.close()
    assert publisher.images, "nothing was rendered"
    assert publisher.images[-1].shape == (90, 160, 3)
    assert threading.get_ident() not in publisher.threads
    assert listener.errors == 0


# ------------------------------------------------------------------ item 1 (runner) / 8
def test_an_operator_error_is_a_hold_of_every_effector_not_an_exit():
    loop = trace_loop()
    command, observe = loop.operator.command, loop.operator.observe
    calls = {"command": 0, "observe": 0}

    def flaky_command(now):
        calls["command"] += 1
        if calls["command"] in (20, 21, 22):
            raise ValueError("retarget got NaN")
        return command(now)

    def flaky_observe(frame):
        calls["observe"] += 1
        if calls["observe"] == 80:
            raise FloatingPointError("bad frame")
        observe(frame)

    loop.operator.command, loop.operator.observe = flaky_command, flaky_observe
    ticks = []
    loop.listeners.append(ticks.append)
    q_before = None
    try:
        summary = loop.run(max_seconds=2.0)
        q_before = ticks[18].state.action
    finally:
        loop.twin.env.close()
    assert summary.ticks == 60
    errors = [i for i, t in enumerate(ticks) if t.commands["right"].reason == "error"]
    assert len(errors) == 4 and errors[:3] == [19, 20, 21], errors
    held = ticks[19].commands["right"]
    assert held.hold and np.array_equal(held.positions, q_before)  # the last target, no jump
    assert summary.holds["right"]["error"] == 4
    assert ticks[-1].commands["right"].reason == ""  # tracking again


def test_holds_are_reported_per_effector_with_guard_refusals_and_step_limits():
    loop = trace_loop()
    apply = loop.twin.apply
    n = {"ticks": 0}

    def guarded_apply(commands):
        state = apply(commands)
        n["ticks"] += 1
        if n["ticks"] % 5 == 0:
            state = dataclasses.replace(
                state, guard_blocked=True, guard_blocked_effectors=("right",)
            )
        return state

    loop.twin.apply = guarded_apply
    loop.twin.step_limited = {"right": 7}
    try:
        summary = loop.run(max_seconds=1.0)
    finally:
        loop.twin.env.close()
    right = summary.holds["right"]
    assert right["guard"] == 6 and right["step_limit"] == 7
    assert set(summary.holds) == {"right"}


# ------------------------------------------------------------------ Quest streams
def _trace_frames(task: str = "PickupBox"):
    return [f for _, k, f in TraceReader(bundled_trace(task)).events() if k == "hand"]


def _untracked_tip(frame, joint: int = 10):
    """``frame`` with the index tip untracked (the Quest app sends it as 0,0,0)."""
    tracked = frame.tracked.copy()
    tracked[joint] = False
    return dataclasses.replace(
        frame, joints=np.where(tracked[:, None], frame.joints, np.nan), tracked=tracked
    )


def _quest_stream(first: int = 60, n: int = 150, gap_at: int = 60, gap: int = 6):
    """Keypoint strings of the right hand as the app sends them; frames ``gap_at`` to
    ``gap_at + gap`` have the index tip untracked."""
    from beavr_sim.headset.quest_protocol import format_keypoints

    out = []
    for i, frame in enumerate(_trace_frames()[first : first + n]):
        if gap_at <= i < gap_at + gap:
            frame = _untracked_tip(frame)
        out.append(format_keypoints(frame).encode())
    return out


def test_an_untracked_fingertip_from_the_quest_holds_the_finger_in_process(
    quest_push, quest_options
):
    """The right index tip sent as 0,0,0 for six frames (the real parser flags it untracked):
    the session goes on, the index finger holds, then follows the hand again."""
    options = quest_options()
    transport, context = options.transport, zmq.Context()
    loop = build_loop(options, context)
    push = quest_push(context, transport)
    ticks = []
    try:
        for i, payload in enumerate(_quest_stream()):
            push.send(payload)
            time.sleep(1 / 60)
            if i % 2:
                ticks.append(loop.tick())
        summary = loop.summary(success=False)
    finally:
        push.close()
        loop.source.close()
        loop.twin.env.close()
        context.term()
    gap = [i for i, t in enumerate(ticks) if any(not f.tracked[10] for f in t.frames)]
    assert gap, "no frame with the index tip untracked reached the operator"
    assert not any(t.commands["right"].reason == "error" for t in ticks), summary.holds
    for i in gap:
        index = ticks[i].commands["right"].positions[INDEX]
        np.testing.assert_allclose(index, ticks[i - 1].commands["right"].positions[INDEX])
    after = ticks[gap[-1] + 1 :]
    assert after and not after[-1].commands["right"].hold, after[-1].commands["right"]
    moved = np.ptp([t.commands["right"].positions[INDEX] for t in after], axis=0).max()
    assert moved > 1e-3, "the index finger did not follow the hand again"
    assert all(np.isfinite(t.commands["right"].positions).all() for t in ticks)


def _multiprocess(source: str, **kwargs):
    from beavr_sim.teleop.processes import MultiprocessSession

    options = SessionOptions(
        task="PickupBox",
        source=source,
        viser=False,
        headless=True,
        progress=False,
        multiprocess=True,
        transport=TransportConfig(ports=PortConfig.free()),
        **kwargs,
    )
    return MultiprocessSession(options)


def test_an_untracked_fingertip_from_the_quest_in_multiprocess(quest_push):
    from beavr_sim.wire.messages import JointCommandMsg
    from beavr_sim.wire.transport import Subscriber

    session = _multiprocess("quest", max_seconds=30)
    transport = session.transport
    session.start()
    context = zmq.Context()
    push = quest_push(context, transport)
    commands = Subscriber(
        context,
        transport.endpoint("commands", bind=False),
        b"right",
        JointCommandMsg,
        conflate=False,
    )
    seen: list = []
    try:
        # The operator commands (holds: waiting) before any hand: the subscription is live.
        wait_until(lambda: (msg := commands.recv(0.05)) is not None and seen.append(msg) is None,
                   "the operator's first command")  # fmt: skip
        for payload in _quest_stream():
            push.send(payload)
            time.sleep(1 / 60)
            while (msg := commands.recv(0.0)) is not None:
                seen.append(msg)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            if (msg := commands.recv(0.05)) is not None:
                seen.append(msg)
        assert session.dead() == [], f"{session.dead()} died"
    finally:
        push.close()
        commands.close()
        context.term()
        session.stop()
    summary_exits = dict(session.exits)
    assert summary_exits["operator"] == 0, summary_exits
    tracking = [m for m in seen if not m.hold]
    assert len(tracking) > 20, "the operator did not follow the hand"
    assert not seen[-1].hold or seen[-1].reason == "tracking_lost", seen[-1]
    assert not any(m.reason == "error" for m in seen)
    assert all(np.isfinite(m.positions).all() for m in seen)
    from beavr_sim.teleop.processes import merged_holds

    holds = merged_holds(session.results["operator"], session.results["twin"])["right"]
    assert "error" not in holds and holds.get("waiting", 0) > 0, holds


# ------------------------------------------------------------------ item 7: reset race
def test_a_reset_in_multiprocess_rehomes_the_operator_to_the_new_pose(quest_push):
    """A headset hand moves the arm away from home, then stays still; after a reset the
    operator continues from the reset pose (the arm stays there), not from a robot state
    published before the reset (the arm would be driven back where it was)."""
    from beavr_sim.headset.quest_protocol import format_keypoints

    session = _multiprocess("quest")
    transport = session.transport
    session.start()
    context = zmq.Context()
    push = quest_push(context, transport)
    frames = _trace_frames()[60:200]
    still = format_keypoints(frames[-1]).encode()
    arm = slice(0, 7)

    def stream_until(done, moving: list | None = None):
        """Send the hand at 60 Hz (moving, then still) until ``done(frames sent, states
        received)``; the states received."""
        states, i, hang_guard = [], 0, time.monotonic() + HANG_GUARD_S
        while not done(i, states):
            assert time.monotonic() < hang_guard, f"{i} frames sent, {len(states)} states"
            push.send(format_keypoints(moving[i]).encode() if moving and i < len(moving) else still)
            i += 1
            time.sleep(1 / 60)
            while (st := session.state_sub.recv(0.0)) is not None:
                states.append(st)
        return states

    def after_reset(states):  # the twin's time starts over at the reset
        return [s for s in states if s.t < before.t - 0.5]

    try:
        stream_until(lambda i, _: i >= len(frames) + 60, frames)  # the arm follows, then stands
        before = stream_until(lambda i, states: i >= 18 and states)[-1]
        session.send("reset")
        # A second of the twin's time after the reset, however long the reset took.
        after = after_reset(
            stream_until(lambda _, states: (a := after_reset(states)) and a[-1].t - a[0].t >= 1.0)
        )
        assert session.dead() == []
    finally:
        push.close()
        context.term()
        session.stop()
    assert after, "no state after the reset"
    home = np.asarray(after[0].positions)[arm]
    away = np.abs(np.asarray(before.positions)[arm] - home).max()
    assert away > 0.2, f"the arm had not moved from home before the reset ({away:.3f} rad)"
    drift = max(np.abs(np.asarray(s.positions)[arm] - home).max() for s in after)
    assert drift < 0.05, (
        f"after the reset the arm moved {drift:.3f} rad (the pre-reset pose is {away:.3f} rad "
        "away): the operator re-homed to a stale pose"
    )
    assert session.results["operator"]["reset_epoch"] == 1
    assert session.results["twin"]["reset_epoch"] == 1


@pytest.mark.parametrize("reason", ["guard", "paused"])
def test_summary_holds_by_effector_shape(reason):
    """The shape the CLI prints: effector -> reason -> ticks."""
    from beavr_sim.teleop.pipeline import count_hold

    holds: dict[str, dict[str, int]] = {}
    count_hold(holds, "right", reason)
    count_hold(holds, "right", reason)
    count_hold(holds, "left", reason)
    assert holds == {"right": {reason: 2}, "left": {reason: 1}}


def test_tick_schedule_skips_the_deadlines_a_stall_passed_and_counts_them():
    from beavr_sim.teleop.pipeline import TickSchedule

    now = [100.0]

    def sleep(s: float) -> None:
        now[0] += s

    schedule = TickSchedule(0.1, clock=lambda: now[0])
    starts = [schedule.wait(sleep)]  # the first tick at once
    now[0] += 0.02
    starts.append(schedule.wait(sleep))  # on its deadline
    now[0] += 0.37  # a stall: 2.5 periods past the next deadline
    starts.append(schedule.wait(sleep))  # at once, late
    now[0] += 0.02
    starts.append(schedule.wait(sleep))  # a period after the late one, not a burst
    np.testing.assert_allclose(np.array(starts) - 100.0, [0.0, 0.1, 0.47, 0.57])
    assert (schedule.overruns, schedule.missed_ticks) == (1, 2)
    now[0] += 5.0  # outside the loop (set-up between runs): not an overrun
    schedule.resume()
    schedule.wait(sleep)
    assert (schedule.overruns, schedule.missed_ticks) == (1, 2)
    with pytest.raises(ValueError, match="positive"):
        TickSchedule(0.0)


def test_the_operator_process_rehomes_only_from_the_reset_epoch():
    from beavr_sim.teleop.operator_process import OperatorRehome
    from beavr_sim.wire.messages import RobotStateMsg

    class Operator:
        def __init__(self):
            self.homes: list[list[float]] = []

        def reset(self, q, slices):
            self.homes.append(list(q))

        def resync(self, name, q):
            raise AssertionError("no guard block here")

    def state(epoch: int, q: float) -> RobotStateMsg:
        return RobotStateMsg(t=0.0, positions=[q, q], velocities=[0.0, 0.0], epoch=epoch)

    now = [0.0]
    op = Operator()
    rehome = OperatorRehome(op, {"right": slice(0, 2)}, clock=lambda: now[0])
    assert rehome.waiting  # no state yet: hold
    rehome.on_state(state(0, 1.0))
    assert not rehome.waiting and op.homes == [[1.0, 1.0]]
    rehome.expect(1)  # the supervisor's reset
    rehome.on_state(state(0, 2.0))  # published before the reset: ignored
    assert rehome.waiting and op.homes == [[1.0, 1.0]]
    now[0] = 5.0
    rehome.warn_if_late(now[0])  # logs, keeps holding
    assert rehome.waiting
    rehome.on_state(state(1, 0.0))
    assert not rehome.waiting and op.homes[-1] == [0.0, 0.0] and rehome.epoch == 1
    rehome.on_state(state(2, 3.0))  # a reset from the twin's browser view
    assert op.homes[-1] == [3.0, 3.0] and rehome.epoch == 2
    rehome.expect(2)  # a reset request the twin has already done: nothing to wait for
    assert not rehome.waiting


def test_epochs_on_the_wire_are_checked():
    from beavr_sim.wire.messages import JointCommandMsg, SessionMsg, decode, encode

    msg = SessionMsg(command="reset", epoch=3)
    assert decode(encode(msg), SessionMsg).epoch == 3
    with pytest.raises(ValueError, match="epoch"):
        JointCommandMsg(effector="right", t_source=0.0, t_command=0.0, positions=[], hold=True,
                        epoch=-1)  # fmt: skip


def test_the_cli_says_why_each_effector_held():
    from beavr_sim.teleop.__main__ import explain

    lines = explain(
        {
            "holds": {"right": {"guard": 3, "paused": 12}, "left": {"tracking_lost": 4}},
            "listener_errors": {"headset_images": 2},
            "overruns": 1,
            "missed_ticks": 9,
        }
    )
    assert lines[0] == "left held (ticks by reason): tracking_lost 4"
    assert lines[1] == "right held (ticks by reason): paused 12, guard 3"
    assert "headset_images 2" in lines[2] and "9 control periods skipped" in lines[3]
    assert explain({"holds": {}}) == []


def test_every_reset_gives_the_operators_ik_the_tasks_fixtures():
    """The in-process loop hands the fixtures the reset placed (Tape's box) to every arm IK,
    anew at each reset (the box moves with the seed)."""
    from beavr_sim.operator.obstacles import fixture_obstacles

    options = SessionOptions(task="Tape", source="trace", viser=False, headless=True)
    loop = build_loop(options)
    try:
        env = loop.twin.env
        poses = []
        for seed in (0, 1):
            loop.reset(seed)
            expected = fixture_obstacles(env.model, env.data)
            assert expected, "Tape has a box"
            for op in loop.operator.effectors.values():
                assert op.ik.obstacles == expected
            poses.append(expected[0].pos)
        assert poses[0] != poses[1]
    finally:
        loop.source.close()
        loop.twin.env.close()
