"""The hardware mirror through whole sessions on the emulated rig (the vendors' SDKs against our
protocol emulators in their own process): several episodes with resets, short and long outages
(the emulator process frozen), re-arming, the summary, and bounded statistics.

The contract: a reset never latches a divergence hold (a device is judged against what it was
sent); a device that stops answering holds the whole rig and resumes when it answers again
where it was held within ``reconnect_s``, else it stays failed until re-armed; after a re-arm
it follows again; the summary says what happened; memory does not grow with the writes.

Every wait is for a state (a readiness wait; the bound is a hang guard only).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import time
import tracemalloc
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.hardware.device import DeviceError
from beavr_sim.hardware.mirror import (
    WRITE_LOG_SIZE,
    Fixtures,
    HardwareMirror,
    HoldReason,
    LinkState,
)
from beavr_sim.hardware.rig import EmulatedRig, MirrorConfig
from beavr_sim.teleop.mirroring import BrowserEstop
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand

#: Hang guard for state waits (s): never reached unless something is broken.
HANG_S = 60.0


class Session:
    """A twin, the emulated rig of its embodiment (a child process) and a mirror of it, ticked
    in real time as the session's loop ticks it."""

    def __init__(
        self, task: str = "PickupBox", devices: slice | None = None, dry_run=False, **mirror_fields
    ):
        self.env = gym.make(f"beavr_sim/{task}-v0").unwrapped
        self.twin = TwinInterface(self.env)
        self.twin.reset(seed=0)
        self.rig = EmulatedRig(self.env.embodiment, self.env.joints)
        config = self.rig.config
        if devices is not None:
            config = dataclasses.replace(config, devices=config.devices[devices])
        if mirror_fields:
            config = dataclasses.replace(
                config, mirror=dataclasses.replace(config.mirror, **mirror_fields)
            )
        self.mirror = HardwareMirror(
            config,
            self.env.embodiment,
            self.env.joints,
            self.env.model,
            self.env.control_hz,
            dry_run=dry_run,
        )
        q = self.mirror.connect()
        self.twin.reset(seed=0, robot_qpos=q)
        self.mirror.start(self.twin.action)
        self.period = 1.0 / self.env.control_hz
        self.frozen = False

    def tick(self, target: np.ndarray | None = None):
        """One control period: a command (or none) through the twin, its action to the mirror."""
        commands = {}
        if target is not None:
            sl = self.twin.slices["right"]
            commands["right"] = JointCommand("right", target[sl], t_source=0.0, t_receive=0.0)
        state = self.twin.apply(commands)
        self.mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
        time.sleep(self.period)
        return state

    def tick_until(self, predicate, what: str, target: np.ndarray | None = None) -> None:
        deadline = time.monotonic() + HANG_S
        while not predicate():
            assert time.monotonic() < deadline, f"hang guard: never {what}"
            self.tick(target)

    def reset(self, seed: int) -> np.ndarray:
        """A new episode: the twin jumps to its home pose; the mirror is told."""
        q_start = self.twin.reset(seed=seed)
        self.mirror.begin_episode(q_start, Fixtures.of(self.env.data))
        return q_start

    def state(self, name: str) -> LinkState:
        return next(d.state for d in self.mirror.health().devices if d.name == name)

    def freeze(self) -> None:
        os.kill(self.rig._process.pid, signal.SIGSTOP)
        self.frozen = True

    def thaw(self) -> None:
        os.kill(self.rig._process.pid, signal.SIGCONT)
        self.frozen = False

    def close(self) -> None:
        if self.frozen:
            self.thaw()
        self.mirror.close()
        self.rig.close()
        self.env.close()


@pytest.fixture
def session():
    s = Session()
    yield s
    s.close()


def _divergence_holds(summary: dict) -> int:
    return sum(d["holds"] - d["timeout_holds"] for d in summary.values())


def test_episodes_with_resets_never_latch_a_divergence(session):
    """Three episodes: the arm swings 1.2 rad away, the twin is reset home (a jump the devices
    follow at the catch-up speed, 2.4 s), and every episode starts in sync: no device ever
    holds for divergence (on today's main the first reset latched ``diverged: 1.2 rad`` and
    the arm held for the rest of the session)."""
    mirror = session.mirror
    names = [link.name for link in mirror.links]
    for episode in range(3):
        q_start = session.reset(seed=episode)
        session.tick_until(mirror.in_sync, "in sync at the episode's start")
        health = mirror.health()
        assert health.live and health.episode_faults == (), health
        np.testing.assert_allclose(mirror.latest_measured()[:7], q_start[:7], atol=0.05)
        target = session.twin.action.copy()
        for _ in range(36):  # joint 1 at 1 rad/s for 1.2 s (the twin's cap is pi)
            target[0] += 1.0 * session.period
            session.tick(target)
            health = mirror.health()
            assert not health.episode_faults, health
        session.tick_until(
            lambda goal=target[0]: abs(mirror.latest_measured()[0] - goal) < 0.05, "arm there"
        )
        for name in names:
            assert session.state(name) is LinkState.FOLLOWING, mirror.health()
    summary = mirror.summary()
    assert _divergence_holds(summary) == 0, summary
    # Two resets from 1.2 rad away: 1.1 rad each at the catch-up speed (the last tenth within
    # a period's motion), 66 ticks at 30 Hz.
    assert summary["right_arm"]["catch_up_steps"] >= 2 * 60
    assert summary["right_arm"]["max_divergence_rad"] < mirror.rig.mirror.arm_divergence_rad
    assert mirror.failed_devices == []


def test_the_catch_up_is_refused_where_it_would_cross_this_episodes_fixture():
    """The mirror's own guard checks the catch-up against the fixtures of the episode it was
    told about: a cup placed where the hand's home pose is stops the catch-up short of it
    (the devices hold those joints; never in sync); the next episode's cup elsewhere lets it
    through."""
    s = Session("Pour")
    try:
        mirror = s.mirror
        env = s.env
        target = s.twin.action.copy()
        target[0] += 0.6  # the arm turned away, the devices there
        s.tick_until(
            lambda: abs(mirror.latest_measured()[0] - target[0]) < 0.02, "the arm away", target
        )
        q_home = s.twin.reset(seed=0)
        palm = env.data.body("right/palm").xpos.copy()  # the twin at home, after its reset
        cup = env.model.body("target_cup").mocapid[0]
        fixtures = Fixtures.of(env.data)
        fixtures.mocap_pos[cup] = palm  # this episode's cup: where the hand will be
        mirror.begin_episode(q_home, fixtures)
        s.tick_until(lambda: mirror.summary()["right_arm"]["catch_up_refused"] > 0, "refused")
        held = mirror.latest_measured()[0]
        for _ in range(15):
            s.tick()
            assert not mirror.in_sync()
        assert abs(mirror.latest_measured()[0] - q_home[0]) > 0.05  # short of home
        assert abs(mirror.latest_measured()[0] - held) < 0.05  # held there
        q_home = s.twin.reset(seed=0)
        mirror.begin_episode(q_home, Fixtures.of(env.data))  # the cup back on the table
        s.tick_until(mirror.in_sync, "in sync")
        assert mirror.health().live
    finally:
        s.close()


def test_a_short_freeze_holds_the_rig_and_resumes(session):
    """The emulators stop answering for 2.5 s (their process stopped: a USB hub, a controller
    that hangs for a moment): every device holds, the ones that noticed are reconnected, and
    when they answer again where they were held the rig follows again (on today's main both
    devices were marked failed for good)."""
    mirror = session.mirror
    session.tick_until(mirror.in_sync, "in sync")
    q_held = mirror.latest_measured()
    session.freeze()
    session.tick_until(lambda: mirror.health().failed, "a device noticed")
    assert not mirror.health().live
    t_frozen = time.monotonic()
    while time.monotonic() - t_frozen < 2.5:  # the twin ticks on (the operator holds still)
        session.tick()
        assert not mirror.health().live
    session.thaw()
    session.tick_until(lambda: mirror.health().live and mirror.in_sync(), "resumed")
    summary = mirror.summary()
    assert mirror.failed_devices == []
    assert sum(d["outages"] for d in summary.values()) >= 1, summary
    assert sum(d["recovered"] for d in summary.values()) == sum(
        d["outages"] for d in summary.values()
    )
    faults = mirror.health().episode_faults
    assert any("stopped answering" in f for f in faults), faults
    np.testing.assert_allclose(mirror.latest_measured()[:7], q_held[:7], atol=0.02)
    # It follows again.
    target = session.twin.action.copy()
    target[0] += 0.2
    session.tick_until(
        lambda: abs(mirror.latest_measured()[0] - target[0]) < 0.02, "following", target
    )


def test_a_long_outage_fails_until_rearmed_then_follows():
    """Frozen for longer than ``reconnect_s``: the devices fail, a re-arm while they still do
    not answer leaves them failed, and they stay failed when the emulators answer again (the
    operator must look first); re-armed from the browser view's release button, they follow
    again."""
    s = Session(reconnect_s=0.6)
    try:
        mirror = s.mirror
        s.tick_until(mirror.in_sync, "in sync")
        s.freeze()
        s.tick_until(
            lambda: any(d.state is LinkState.FAILED for d in mirror.health().devices), "failed"
        )
        s.tick_until(
            lambda: all(d.state is not LinkState.OUTAGE for d in mirror.health().devices),
            "every outage decided",
        )
        failed = [d for d in mirror.health().devices if d.state is LinkState.FAILED]
        assert all(d.reason is HoldReason.NO_ANSWER for d in failed), failed
        assert mirror.rearm(timeout_s=HANG_S) == mirror.failed_devices != []  # still frozen
        s.thaw()
        # Answering again does not resume a failed device: ticks go on, it stays out and
        # the rest of the rig holds.
        for _ in range(10):
            s.tick()
        assert mirror.failed_devices and not mirror.health().live
        for d in mirror.health().devices:
            assert d.state in (LinkState.FAILED, LinkState.HOLDING), d
        # The browser's button shows the failed rig as latched; its release re-arms it.
        view = SimpleNamespace(estop_requested=False)
        view.set_estop = lambda latched: setattr(view, "estop_requested", latched)
        button = BrowserEstop(view, mirror)
        button(None)
        assert view.estop_requested
        view.estop_requested = False  # clicked
        button(None)
        s.tick_until(lambda: mirror.health().live and mirror.in_sync(), "re-armed, in sync")
        button(None)
        assert not view.estop_requested and not mirror.estopped
        target = s.twin.action.copy()
        target[0] += 0.2
        s.tick_until(
            lambda: abs(mirror.latest_measured()[0] - target[0]) < 0.02, "following", target
        )
        summary = mirror.summary()
        assert sum(d["rearmed"] for d in summary.values()) == len(failed)
        assert all(d["state"] == "following" for d in summary.values()), summary
        assert mirror.failed_devices == []
    finally:
        s.close()


def test_a_device_that_moved_while_out_stays_failed(session, monkeypatch):
    """A device that answers again away from where it was held (someone moved it) fails."""
    mirror = session.mirror
    session.tick_until(mirror.in_sync, "in sync")
    hand = mirror.links[1].device
    read, reconnect = hand.read_positions, hand.reconnect
    calls = {"n": 0}

    def read_once_failing():
        calls["n"] += 1
        if calls["n"] == 1:
            raise DeviceError("right_hand: no present position (test)")
        return read()

    monkeypatch.setattr(hand, "read_positions", read_once_failing)
    monkeypatch.setattr(hand, "reconnect", lambda: reconnect() + 0.5)
    session.tick_until(lambda: session.state("right_hand") is LinkState.FAILED, "failed")
    (device,) = [d for d in mirror.health().devices if d.name == "right_hand"]
    assert device.reason is HoldReason.MOVED and "moved" in device.detail
    assert mirror.failed_devices == ["right_hand"]
    session.tick_until(lambda: session.state("right_arm") is LinkState.HOLDING, "arm holds")
    (arm,) = [d for d in mirror.health().devices if d.name == "right_arm"]
    assert arm.reason is HoldReason.OTHER_DEVICE


def test_the_summary_says_what_happened(caplog):
    """After close: every device reads connected (it was, during the run), with its state,
    reason, outages, recoveries and retries; device errors are one log line each."""
    s = Session(reconnect_s=5.0)
    try:
        mirror = s.mirror
        s.tick_until(mirror.in_sync, "in sync")
        with caplog.at_level(logging.INFO, logger="beavr_sim.hardware.mirror"):
            s.freeze()
            s.tick_until(lambda: mirror.health().failed, "a device noticed")
            s.thaw()
            s.tick_until(lambda: mirror.health().live, "resumed")
    finally:
        s.close()
    summary = mirror.summary()
    for name, d in summary.items():
        assert d["connected"] and not d["connected_now"], name
        for key in ("outages", "recovered", "retries", "rearmed", "timeout_holds"):
            assert isinstance(d[key], int), (name, key)
        assert d["state"] == "following" and d["reason"] == "none", (name, d)
    assert sum(d["outages"] for d in summary.values()) >= 1
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors and not any(r.exc_info for r in errors)  # no tracebacks (not DEBUG)
    assert all("\n" not in r.getMessage() for r in errors)


def test_write_statistics_stay_bounded():
    """The write log keeps the last WRITE_LOG_SIZE writes for its percentiles and counts all:
    memory does not grow with the writes (today's lists grew about 20 MB an hour)."""
    from beavr_sim.hardware.mirror import DeviceStats

    stats = DeviceStats()
    for k in range(1000):
        stats.writes.add(float(k), 1.0)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for k in range(1000, 1000 + 3 * WRITE_LOG_SIZE):
            stats.writes.add(k * 0.01, 1.0 + (k % 7))
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 10_000, grown
    summary = stats.summary()
    assert summary["write_latency_ms"]["n"] == 1000 + 3 * WRITE_LOG_SIZE
    assert summary["write_latency_ms"]["window"] == WRITE_LOG_SIZE
    assert summary["write_latency_ms"]["p99"] == 7.0
    assert len(stats.write_times) == WRITE_LOG_SIZE
    assert stats.write_times == sorted(stats.write_times)  # oldest first


def test_a_mirror_that_writes_for_long_keeps_what_it_keeps_bounded():
    """Through the mirror (dry run: every dispatch is taken, nothing written): past
    WRITE_LOG_SIZE writes it keeps the last WRITE_LOG_SIZE write times and latencies and
    counts all of them (today every write appended to two lists for the whole session)."""
    s = Session(devices=slice(1, 2), dry_run=True)  # the hand alone: no stream to wait for
    try:
        mirror = s.mirror
        (hand,) = mirror.links
        q = s.twin.action.copy()
        n = WRITE_LOG_SIZE + 500
        for k in range(n):
            q[10] = s.twin.action[10] + (1e-3 if k % 2 else 0.0)
            n0 = hand.stats.writes.count
            mirror.submit(q, q)
            deadline = time.monotonic() + HANG_S
            while hand.stats.writes.count == n0:  # taken (each dispatch waits for its write)
                assert time.monotonic() < deadline
                time.sleep(0.0001)
        summary = mirror.summary()["right_hand"]
        assert summary["write_latency_ms"]["n"] >= n
        assert summary["write_latency_ms"]["window"] == WRITE_LOG_SIZE
        assert len(hand.stats.write_times) == len(hand.stats.write_latency_ms) == WRITE_LOG_SIZE
        assert summary["write_rate_hz"] > 0
    finally:
        s.close()


def test_mirror_settings_are_validated():
    assert MirrorConfig().reconnect_s == 5.0
    for field, bad in (
        ("reconnect_s", 0.0),
        ("reconnect_s", float("inf")),
        ("sync_timeout_s", -1.0),
        ("arm_sync_tolerance_rad", "0.1"),
        ("device_lag_s", True),
    ):
        with pytest.raises(ValueError, match=f"mirror.{field}"):
            MirrorConfig(**{field: bad})
    with pytest.raises(ValueError, match=r"hand_sync_tolerance_rad .* must not exceed"):
        MirrorConfig(hand_sync_tolerance_rad=1.0, hand_divergence_rad=0.5)
