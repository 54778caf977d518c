"""The event-driven pipeline (issue 20): a command per hand frame, on arrival, in one process
and in ``--multiprocess``; every valid frame counted; the twin's command / step split."""

from __future__ import annotations

import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import zmq

import beavr_sim  # noqa: F401
from beavr_sim.assets import bundled_trace
from beavr_sim.headset.quest_protocol import format_keypoints
from beavr_sim.teleop.session import build_loop
from beavr_sim.traces.format import TraceReader
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand

#: Frames of the 90 Hz stream the tests send (one second).
N_FRAMES = 90
#: Hang guard (s) of each wait for the pipeline to take a frame (a readiness wait).
WAIT_S = 30.0


def _payloads(n: int) -> list[bytes]:
    frames = [f for _, k, f in TraceReader(bundled_trace("PickupBox")).events() if k == "hand"]
    return [format_keypoints(f).encode() for f in frames[30 : 30 + n]]


def _send_in_step(push, payloads: list[bytes], sent: list[float], taken) -> None:
    """Send the frames at up to 90 Hz, each only once the pipeline took the one before
    (``taken(k, t_sent)`` waits until frame ``k``, sent at ``t_sent``, was taken): frames
    never bunch, however loaded the machine, so every one is commanded on its own."""
    start = time.monotonic()
    for k, payload in enumerate(payloads):
        time.sleep(max(0.0, start + k / 90.0 - time.monotonic()))  # the stream's rate
        sent.append(time.monotonic())
        push.send(payload)
        if not taken(k, sent[-1]):
            raise TimeoutError(f"frame {k} was not taken within {WAIT_S} s")


def test_a_90_hz_quest_stream_gets_a_command_per_frame_in_one_process(quest_push, quest_options):
    options = quest_options()
    transport, context = options.transport, zmq.Context()
    loop = build_loop(options, context)
    applied: list[float] = []  # when each command reached the twin's actuators
    per_tick: list[int] = []  # commands applied by the end of each tick
    progress = threading.Condition()

    def on_command(outcome, cmds) -> None:
        applied.append(loop.twin.applied_monotonic)
        with progress:
            progress.notify_all()

    loop.command_hooks.append(on_command)
    loop.listeners.append(lambda tick: per_tick.append(len(applied)))

    def taken(k: int, _t_sent: float) -> bool:
        with progress:
            return progress.wait_for(lambda: loop.frame_commands > k, timeout=WAIT_S)

    push = quest_push(context, transport)
    sent: list[float] = []
    failed: list[BaseException] = []

    def send() -> None:
        try:
            _send_in_step(push, _payloads(N_FRAMES), sent, taken)
        except BaseException as exc:
            failed.append(exc)

    sender = threading.Thread(target=send)
    try:
        sender.start()
        while sender.is_alive():
            loop.tick()
        summary = loop.summary(success=False)
    finally:
        sender.join()
        push.close()
        loop.source.close()
        loop.twin.env.close()
        context.term()
    assert not failed, failed
    assert len(sent) == N_FRAMES
    # Every valid frame is counted and, arriving on its own, commanded on arrival.
    assert summary.frames_received == N_FRAMES, summary
    assert loop.frame_commands == N_FRAMES and summary.frames_superseded == 0, summary
    # The commands did not wait for a physics tick: some tick took several of them.
    assert max(b - a for a, b in zip([0, *per_tick], per_tick, strict=False)) >= 2, per_tick
    assert applied == sorted(applied)
    assert summary.latency_ms["n"] >= 0.8 * N_FRAMES


def test_a_90_hz_quest_stream_gets_a_command_per_frame_across_processes(quest_push, quest_options):
    from beavr_sim.teleop.processes import MultiprocessSession
    from beavr_sim.wire.messages import JointCommandMsg
    from beavr_sim.wire.transport import Subscriber

    options = quest_options(multiprocess=True)
    transport = options.transport
    session = MultiprocessSession(options)
    session.start()
    context = zmq.Context()
    push = quest_push(context, transport)
    # The operator's commands as the twin gets them: frame k was taken once a command
    # carries its time (t_source: its arrival, after it was sent).
    commands = Subscriber(
        context,
        transport.endpoint("commands", bind=False),
        b"right",
        JointCommandMsg,
        conflate=False,
    )

    def taken(_k: int, t_sent: float) -> bool:
        deadline = time.monotonic() + WAIT_S
        while (left := deadline - time.monotonic()) > 0:
            msg = commands.recv(left)
            if msg is not None and msg.t_source >= t_sent:
                return True
        return False

    sent: list[float] = []
    try:
        # Subscribed: the operator commands the idle hand every control period.
        assert commands.recv(WAIT_S) is not None, "no command from the operator process"
        _send_in_step(push, _payloads(N_FRAMES), sent, taken)
        assert session.dead() == []
    finally:
        commands.close()
        push.close()
        context.term()
        session.stop()
    op, twin = session.results["operator"], session.results["twin"]
    det = op["detector"]  # the detector runs in the operator's process
    assert det["frames_received"] == N_FRAMES, det
    assert det["frames_rejected"] == 0
    commanded, superseded = op["frames_commanded"]["right"], op["frames_superseded"]["right"]
    assert commanded == N_FRAMES and superseded == 0, op
    assert twin["commands_applied"] > 0, twin  # the twin applied them (its rate: bench latency)
    assert session.summary().frames_superseded == superseded


# ---------------------------------------------------------------------------- twin
def _twin(seed: int = 0) -> TwinInterface:
    env = gym.make("beavr_sim/PickupBox-v0", embodiment="xarm7_leap_right").unwrapped
    twin = TwinInterface(env)
    twin.reset(seed)
    return twin


def _cmd(q: np.ndarray) -> dict[str, JointCommand]:
    return {"right": JointCommand("right", np.asarray(q, dtype=np.float64).copy(), 0.0, 0.0)}


def test_apply_is_command_then_step_bit_for_bit():
    a, b = _twin(), _twin()
    q = a.action.copy()
    rng = np.random.default_rng(0)
    for _ in range(15):
        q[:7] += rng.uniform(-0.02, 0.02, 7)
        sa = a.apply(_cmd(q))
        b.command(_cmd(q))
        sb = b.step()
        assert np.array_equal(sa.positions, sb.positions)
        assert np.array_equal(sa.action, sb.action)
    assert np.array_equal(a.env.data.qpos, b.env.data.qpos)
    a.env.close()
    b.env.close()


def test_several_commands_per_period_take_effect_at_once_and_the_step_limit_holds():
    twin = _twin()
    stepped = twin.action.copy()
    cap = twin.max_velocity * twin.dt  # one period's motion at the speed cap
    # Three commands in one period, each a 0.6-cap step from the one before: the newest is
    # in the action at once, but no joint ends more than one cap from the last step.
    q = stepped.copy()
    for k in range(1, 4):
        q[0] = stepped[0] + 0.6 * k * cap[0]
        outcome = twin.command(_cmd(q))
        assert outcome.accepted == ("right",)
        expected = stepped[0] + min(0.6 * k, 1.0) * cap[0]
        assert twin.action[0] == pytest.approx(expected, abs=1e-12)
    assert twin.step_limited.get("right", 0) == 2  # the second and third were shortened
    st = twin.step()
    assert st.action[0] == pytest.approx(stepped[0] + cap[0], abs=1e-12)
    # The next period measures from the new step.
    q[0] = st.action[0] + 0.5 * cap[0]
    twin.command(_cmd(q))
    assert twin.action[0] == pytest.approx(q[0], abs=1e-12)
    twin.env.close()


def test_the_guard_refuses_a_command_between_steps_and_the_effector_keeps_its_newest_target():
    twin = _twin()
    q = twin.action.copy()
    q[0] += 0.01
    assert twin.command(_cmd(q)).accepted == ("right",)
    good = twin.action.copy()
    bad = good.copy()
    bad[1] = np.nan  # corrupt: the guard refuses it whole
    outcome = twin.command(_cmd(bad))
    assert outcome.blocked == ("right",) and outcome.accepted == ()
    assert np.array_equal(twin.action, good)
    st = twin.step()
    assert st.guard_blocked_effectors == ("right",)  # reported with the step
    assert np.array_equal(st.action, good)
    twin.env.close()
