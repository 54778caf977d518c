"""Hardware mirroring through the real SDKs against the emulators: what reaches a motor.

The contract: a command the twin's guard refuses never reaches a motor; a device holds on a
timeout, a divergence, an e-stop or another device's failure; mirroring refuses to start when
a device cannot be reached.
"""

from __future__ import annotations

import itertools
import json
import multiprocessing
import time

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.hardware.device import MirrorError
from beavr_sim.hardware.leap.config import (
    RAD_PER_COUNT,
    LeapHandConfig,
    counts_to_model,
    model_to_counts,
)
from beavr_sim.hardware.leap.emulator import DynamixelEmulator
from beavr_sim.hardware.mirror import HardwareMirror
from beavr_sim.hardware.rig import DeviceEntry, MirrorConfig, RigConfig
from beavr_sim.hardware.xarm.config import XArmConfig
from beavr_sim.hardware.xarm.emulator import XArmEmulator
from beavr_sim.teleop.__main__ import main as teleop_main
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand


def wait_for(predicate, timeout: float = 30.0, poll_s: float = 0.005) -> None:
    """Until ``predicate()`` holds (a readiness wait: the bound is only a hang guard)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(poll_s)


class FakeClock:
    """The mirror's clock for submit spacing, advanced by hand (the writers keep real time)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


class Bench:
    """A PickupBox twin, in-process emulators of its arm and hand, and a mirror of them."""

    def __init__(
        self, mirror_config: MirrorConfig | None = None, dry_run: bool = False, clock=None
    ):
        self.env = gym.make("beavr_sim/PickupBox-v0").unwrapped
        # Without a clock of the test's own, each step() stands for exactly one control period
        # (lockstep), however fast or slow this machine runs the test.
        self._lockstep_clock = FakeClock() if clock is None else None
        self.twin = TwinInterface(self.env)
        self.twin.reset(seed=0)
        joints = self.env.joints
        home = joints.home.astype(np.float64)
        self.arm = XArmEmulator(initial_joints=tuple(home[:7]))
        counts = model_to_counts(home[7:])
        self.hand = DynamixelEmulator(initial_position=dict(enumerate(counts))).start()
        rig = RigConfig(
            (
                DeviceEntry(
                    "right_arm",
                    "xarm7",
                    "right",
                    XArmConfig(host=self.arm.host, port=self.arm.port, max_joint_speed=np.pi),
                ),
                DeviceEntry(
                    "right_hand",
                    "leap",
                    "right",
                    LeapHandConfig(self.hand.port, reply_timeout_s=0.25),
                ),
            ),
            mirror_config or MirrorConfig(hand_divergence_rad=2.5),
        )
        self.mirror = HardwareMirror(
            rig,
            self.env.embodiment,
            joints,
            self.env.model,
            self.env.control_hz,
            dry_run=dry_run,
            clock=clock or self._lockstep_clock,
        )
        q = self.mirror.connect()
        self.twin.reset(seed=0, robot_qpos=q)
        self.mirror.start(self.twin.action)
        self.accepted = [self.twin.action.copy()]

    def step(self, positions, settle: bool = True):
        """One tick: the command through the twin (guard), the result to the mirror."""
        state = self.twin.apply(
            {"right": JointCommand("right", np.asarray(positions), t_source=0.0, t_receive=0.0)}
        )
        if self._lockstep_clock is not None:
            self._lockstep_clock.advance(1.0 / self.env.control_hz)
        self.mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
        self.accepted.append(state.action.copy())
        if settle:
            self.wait_written()
        return state

    def wait_written(self, timeout: float = 30.0) -> None:
        """Until every writer finished with the newest dispatch (written whole, every step of
        a stream out; held; or judged unchanged) and the hand's emulator handled every byte
        it was sent (a sync write has no reply). A readiness wait: ``timeout`` is a hang
        guard."""
        m = self.mirror
        hand = next(link.device for link in m.links if link.device.name == "right_hand")
        wait_for(
            lambda: (
                all(link.seq_served == m.dispatched.seq for link in m.links)
                and self.hand.caught_up(hand.bytes_sent)
            ),
            timeout,
            poll_s=0.002,
        )

    def submit_at(self, clock: FakeClock, dt: float, action, settle: bool = True) -> np.ndarray:
        """An event-driven submit ``dt`` of (injected) time after the previous one, straight
        to the mirror (twin positions = the action); returns the dispatched target."""
        clock.advance(dt)
        action = np.asarray(action, dtype=np.float64)
        self.mirror.submit(action, action)
        if settle:
            self.wait_written()
        return self.mirror.dispatched.target.copy()

    def arm_targets(self) -> np.ndarray:
        return np.array([q for _, q in self.arm.servo_log]).reshape(-1, 7)

    def hand_goals(self) -> np.ndarray:
        """Every complete set of the 16 goals as written (a sync write, or the 16 single
        writes at connect), in model radians."""
        rows, current = [], {}
        for _, motor, counts in self.hand.goal_log:
            if motor in current:
                current = {}
            current[motor] = counts
            if len(current) == 16:
                rows.append(counts_to_model(np.array([current[i] for i in range(16)])))
                current = {}
        return np.array(rows).reshape(-1, 16)

    def close(self) -> None:
        self.mirror.close()
        self.arm.close()
        self.hand.close()
        self.env.close()


def on_accepted_path(targets: np.ndarray, accepted: list[np.ndarray], part: slice, tol: float):
    """Each target lies on the segment between two consecutive accepted actions (the
    interpolated stream) or at one of them."""
    points = np.array([a[part] for a in accepted])
    bad = []
    for q in targets:
        ok = False
        for a, b in itertools.pairwise(points):
            d = b - a
            s = 0.0 if not d.any() else float(np.clip(np.dot(q - a, d) / np.dot(d, d), 0, 1))
            if np.abs(a + s * d - q).max() <= tol:
                ok = True
                break
        ok = ok or np.abs(points - q).max(axis=1).min() <= tol
        if not ok:
            bad.append(q)
    return bad


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def test_adversarial_commands_never_reach_a_motor(bench):
    env = bench.env
    home = bench.twin.action.copy()
    lower, upper = env.joints.lower, env.joints.upper
    into_table = home.copy()
    into_table[1], into_table[3] = 1.45, 1.2  # the hand down through the table, in one go
    past_limit = home.copy()
    past_limit[3] = upper[3] + 0.3
    fingers_through_palm = home.copy()
    fingers_through_palm[7:] = upper[7:]  # every finger joint at its end: fingers collide
    jump = home.copy()
    jump[0] += 1.0
    nan = home.copy()
    nan[5] = np.nan
    cap = bench.twin.max_velocity * bench.twin.dt * (1 + 1e-9)
    for bad in (into_table, past_limit, fingers_through_palm, nan):
        # Corrupt targets are refused at once; unsafe ones are approached at the twin's step
        # limit until the guard refuses the next step.
        for _ in range(30):
            before = bench.twin.action.copy()
            state = bench.step(bad)
            assert (np.abs(state.action - before) <= cap).all()
            if state.guard_blocked:
                break
        assert state.guard_blocked_effectors == ("right",), bad
        while np.abs(bench.twin.action - home).max() > 0:  # back home at the speed cap
            assert not bench.step(home).guard_blocked
    # A 1 rad jump is a legal move at the speed cap: 10 ticks of at most pi / 30.
    for _ in range(10):
        before = bench.twin.action.copy()
        state = bench.step(jump)
        assert not state.guard_blocked and (np.abs(state.action - before) <= cap).all()
    np.testing.assert_array_equal(state.action, jump)
    while np.abs(bench.twin.action - home).max() > 0:
        bench.step(home)
    # A legal, slow move afterwards still goes through.
    ok = home.copy()
    ok[0] += 0.03
    assert not bench.step(ok).guard_blocked
    arm = bench.arm_targets()
    hand = bench.hand_goals()
    assert len(arm) and len(hand)
    assert (
        np.isfinite(arm).all()
        and (arm >= lower[:7] - 1e-6).all()
        and (arm <= upper[:7] + 1e-6).all()
    )
    assert not on_accepted_path(arm, bench.accepted, slice(0, 7), 1e-5)
    assert not on_accepted_path(hand, bench.accepted, slice(7, 23), np.pi / 4096 + 1e-9)
    assert np.abs(arm[-1] - ok[:7]).max() < 1e-5
    summary = bench.mirror.summary()
    assert summary["right_arm"]["commands_refused"] == 4
    assert summary["right_hand"]["commands_refused"] == 4
    assert summary["right_arm"]["errors"] == 0 and bench.arm.error_code == 0
    assert summary["right_arm"]["catch_up_steps"] == 0


@settings(
    max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.lists(st.lists(st.floats(-0.3, 0.3), min_size=23, max_size=23), min_size=1, max_size=5),
    st.integers(-1, 4),
)
def test_every_goal_a_motor_received_passed_the_guard(bench, steps, nan_at):
    for k, delta in enumerate(steps):
        command = bench.twin.action + np.asarray(delta)
        if k == nan_at:
            command[k] = np.nan
        bench.step(command)
    assert not on_accepted_path(bench.arm_targets(), bench.accepted, slice(0, 7), 1e-5)
    assert not on_accepted_path(
        bench.hand_goals(), bench.accepted, slice(7, 23), np.pi / 4096 + 1e-9
    )


def test_timeout_estop_and_failure_hold(bench):
    home = bench.twin.action.copy()
    step = home.copy()
    step[0] += 0.03
    bench.step(step)
    t_last = time.monotonic()  # (after the last submit)
    n_arm = len(bench.arm.servo_log)
    # No fresh command: every device holds and says why, soon after the timeout (20 x its
    # 0.25 s: a busy machine delays the writer threads, not by seconds).
    timeout_s = bench.mirror.rig.mirror.command_timeout_s
    wait_for(lambda: all(s["holding"] for s in bench.mirror.summary().values()))
    assert time.monotonic() - t_last < 20 * timeout_s, "no hold within 20 x the timeout"
    summary = bench.mirror.summary()
    for name in ("right_arm", "right_hand"):
        assert (summary[name]["state"], summary[name]["reason"]) == ("holding", "timeout")
        assert summary[name]["holding"].startswith("no fresh command")
    assert all(np.allclose(q, step[:7], atol=1e-5) for _, q in bench.arm.servo_log[n_arm:])
    # Commands again: the devices follow.
    bench.step(home)
    assert bench.mirror.summary()["right_arm"]["state"] == "following"
    # E-stop: latched, nothing new is written until release; then a slow, guarded catch-up.
    bench.mirror.estop("test")
    wait_for(
        lambda: all(s["holding"].startswith("e-stop") for s in bench.mirror.summary().values())
    )
    n_arm, n_hand = len(bench.arm.servo_log), len(bench.hand.goal_log)
    far = home.copy()
    for k in range(1, 6):
        far[0] = home[0] + 0.06 * k
        bench.step(far)
    assert all(np.allclose(q, home[:7], atol=1e-5) for _, q in bench.arm.servo_log[n_arm:])
    summary = bench.mirror.summary()["right_arm"]
    assert (summary["state"], summary["reason"], summary["holding"]) == (
        "holding",
        "estop",
        "e-stop: test",
    )
    assert len(bench.hand.goal_log) - n_hand <= 16  # at most the hold's one re-send
    bench.mirror.release()
    bench.step(far)  # 0.3 rad away: caught up at the catch-up speed, not in one step
    assert bench.mirror.summary()["right_arm"]["catch_up_steps"] >= 1
    cap = bench.mirror.rig.mirror.arm_catch_up_speed / bench.env.control_hz
    assert abs(bench.arm_targets()[-1][0] - home[0]) <= cap + 1e-6
    # A hand bus that vanishes: that device is out (reconnecting), the arm holds, the summary
    # says why.
    bench.hand.vanish()
    deadline = time.monotonic() + 10.0
    while bench.mirror.summary()["right_hand"]["state"] == "following":
        assert time.monotonic() < deadline
        bench.step(far, settle=False)
        time.sleep(0.01)
    summary = bench.mirror.summary()
    assert summary["right_hand"]["errors"] >= 1 and summary["right_hand"]["outages"] == 1
    assert summary["right_hand"]["state"] in ("outage", "failed")
    assert summary["right_hand"]["reason"] in ("device_error", "no_answer")
    bench.mirror.submit(far, far)
    wait_for(lambda: bench.mirror.summary()["right_arm"]["state"] == "holding")
    summary = bench.mirror.summary()
    assert summary["right_arm"]["reason"] == "other_device"
    assert summary["right_arm"]["holding"].startswith("right_hand ")
    assert bench.mirror.failed_devices == ["right_hand"]


def test_divergence_holds_the_device():
    """A device that does not go where it is sent (it measures joint 3 0.3 rad away from its
    targets) holds, latched until a release; the twin's own positions do not matter."""
    bench = Bench(
        MirrorConfig(arm_divergence_rad=0.05, divergence_window_s=0.1, arm_sync_tolerance_rad=0.05)
    )
    try:
        arm = bench.mirror.links[0].device
        read = arm.read_positions
        offset = np.zeros(7)
        offset[2] = 0.3
        arm.read_positions = lambda: read() + offset
        state = bench.twin.apply({})
        deadline = time.monotonic() + 30.0  # submits until the divergence window has passed
        while bench.mirror.summary()["right_arm"]["reason"] != "diverged":
            assert time.monotonic() < deadline
            bench.mirror.submit(state.action, state.positions)
            bench.wait_written()
            time.sleep(0.02)
        summary = bench.mirror.summary()
        assert summary["right_arm"]["state"] == "holding"
        assert summary["right_arm"]["holding"].startswith("diverged: right/joint3")
        assert summary["right_arm"]["max_divergence_joint"] == "right/joint3"
        assert summary["right_arm"]["max_divergence_rad"] >= 0.29
        assert not bench.mirror.health().live
        assert "right_arm diverged" in bench.mirror.health().episode_faults[0]
        # Latched: more commands do not resume it; a release does.
        bench.mirror.submit(state.action, state.positions)
        bench.wait_written()
        assert bench.mirror.summary()["right_arm"]["reason"] == "diverged"
        offset[:] = 0.0
        bench.mirror.release()
        bench.mirror.submit(state.action, state.positions)
        wait_for(lambda: bench.mirror.summary()["right_arm"]["state"] == "following")
    finally:
        bench.close()


def test_unreachable_device_refuses_to_start():
    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    try:
        hand = DynamixelEmulator().start()
        dead = XArmEmulator()
        port = dead.port
        dead.close()
        rig = RigConfig(
            (
                DeviceEntry(
                    "right_arm",
                    "xarm7",
                    "right",
                    XArmConfig("127.0.0.1", port=port, connect_timeout_s=1.0),
                ),
                DeviceEntry("right_hand", "leap", "right", LeapHandConfig(hand.port)),
            )
        )
        mirror = HardwareMirror(rig, env.embodiment, env.joints, env.model, env.control_hz)
        with pytest.raises(MirrorError, match="right_arm"):
            mirror.connect()
        assert not any(link.stats.connected for link in mirror.links)
        hand.close()
    finally:
        env.close()


def test_rig_files_are_validated(tmp_path):
    good = tmp_path / "rig.toml"
    good.write_text(
        """
[mirror]
command_timeout_s = 0.3

[[devices]]
name = "right_arm"
kind = "xarm7"
effector = "right"
host = "192.168.1.185"
reduced_joint_ranges = [[-6.28, 6.28], [-2.0, 2.0], [-6.28, 6.28], [-0.19, 3.9], [-6.28, 6.28], [-1.69, 3.14], [-6.28, 6.28]]

[[devices]]
name = "right_hand"
kind = "leap"
effector = "right"
port = "/dev/ttyUSB0"
variant = "lite"
"""
    )
    rig = RigConfig.from_toml(good)
    assert [d.name for d in rig.devices] == ["right_arm", "right_hand"]
    assert rig.mirror.command_timeout_s == 0.3
    assert rig.devices[1].config.goal_current_ma == 350
    assert rig.devices[0].config.reduced_joint_ranges[1] == (-2.0, 2.0)
    bad = tmp_path / "bad.toml"
    bad.write_text('[[devices]]\nname = "a"\nkind = "xarm8"\neffector = "right"\nhost = "x"\n')
    with pytest.raises(ValueError, match="xarm7"):
        RigConfig.from_toml(bad)
    bad.write_text('[[devices]]\nname = "a"\nkind = "leap"\neffector = "right"\nprt = "/dev/x"\n')
    with pytest.raises(ValueError, match="port"):
        RigConfig.from_toml(bad)
    bad.write_text("[mirror]\ncommand_timeout_s = -1\n[[devices]]\n")
    with pytest.raises(ValueError):
        RigConfig.from_toml(bad)
    with pytest.raises(FileNotFoundError, match="emulated"):
        RigConfig.from_toml(tmp_path / "missing.toml")


def test_pour_trace_mirrored_on_emulated_hardware(tmp_path, capsys, monkeypatch):
    """The bundled pour trace, in real time, mirrored to emulated xArm and LEAP: success, every
    device wrote at the control rate, nothing refused, no errors."""
    import beavr_sim.teleop.session as session

    measured = []
    connect = session.connect_mirror

    def connect_and_keep(*args, **kwargs):
        mirror, q_measured = connect(*args, **kwargs)
        measured.append(np.asarray(q_measured, dtype=np.float64).copy())
        return mirror, q_measured

    monkeypatch.setattr(session, "connect_mirror", connect_and_keep)  # where the session calls it
    out = tmp_path / "summary.json"
    code = teleop_main(
        [
            "--task", "pour", "--source", "trace", "--no-viser", "--headless", "--quiet",
            "--mirror-hardware", "--hardware-config", "emulated", "--summary-json", str(out),
        ]
    )  # fmt: skip
    assert code == 0
    summary = json.loads(out.read_text())
    assert summary["success"]
    hardware = summary["hardware"]
    assert set(hardware) == {"right_arm", "right_hand"}
    for name, device in hardware.items():
        assert device["errors"] == 0 and device["commands_refused"] == 0, name
        assert device["state"] == "following" and device["holding"] == "", name
        # No hold but a command timeout's (the twin paused between the sync and the run on a
        # busy machine: a hold that resumes).
        assert device["holds"] == device["timeout_holds"], (name, device)
        # Each device writes the newest target; under load a writer may merge two ticks.
        assert device["commands_sent"] >= summary["ticks"] * 0.95, name
    assert hardware["right_arm"]["max_divergence_rad"] < 0.3
    # A mirrored trace replays on the paced virtual clock: the same episode as a replay
    # without hardware from the same start (a mirrored episode starts at the task's home pose,
    # once the hardware is there: the sync before it pauses the operator, which its holds
    # count, so those are left out).
    from beavr_sim.teleop.session import SessionOptions, build_loop

    assert len(measured) == 1  # the rig was connected once
    options = SessionOptions(
        task="pour", source="trace", viser=False, headless=True, progress=False
    )
    loop = build_loop(options)
    loop.reset(loop.seed)
    plain = loop.run(stop_on_success=True).to_dict()
    loop.twin.env.close()
    for key in ("ticks", "commands_applied", "frames_received"):
        assert summary[key] == plain[key], key


def test_mirroring_options_are_checked():
    from beavr_sim.teleop.session import SessionOptions

    with pytest.raises(ValueError, match="real control rate"):
        SessionOptions(task="pour", source="trace", mirror_hardware=True, clock="virtual")
    with pytest.raises(ValueError, match="need --mirror-hardware"):
        SessionOptions(task="pour", source="trace", dry_run=True)
    with pytest.raises(ValueError, match="emulated"):
        SessionOptions(task="pour", source="trace", mirror_hardware=True)


def test_recording_while_mirroring_stores_the_measured_hardware_state(tmp_path, capsys):
    """observation.state is what the (emulated) hardware measured: its fingers close on
    nothing and so follow the commands, where the twin's stop on the box they grasp."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path / "rec"
    code = teleop_main(
        [
            "--task", "pickup_box", "--source", "trace", "--no-viser", "--headless", "--quiet",
            "--mirror-hardware", "--hardware-config", "emulated",
            "--record", str(root), "--repo-id", "test/mirrored", "--cameras", "none",
            "--no-keypoints", "--episode-seconds", "7",  # the grasp closes at 4-5.5 s
        ]
    )  # fmt: skip
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["hardware"]["right_hand"]["errors"] == 0
    ds = LeRobotDataset("test/mirrored", root=root)
    state = np.array(ds.hf_dataset["observation.state"])
    action = np.array(ds.hf_dataset["action"])
    assert ds.num_episodes == 1 and len(state) > 100
    # The hand's measured joints trail its commands by a few ticks at most.
    lag = np.abs(state[4:, 7:] - action[:-4, 7:]).max()
    assert lag < 0.5, lag


def test_bimanual_rig_is_the_same_code():
    """Two xArms and two LEAP hands (the paper's bimanual rig), emulated: every device
    connects at the twin's pose and follows its own effector."""
    from beavr_sim.hardware.rig import EmulatedRig

    env = gym.make("beavr_sim/PickPlace-v0", embodiment="xarm7_leap_bimanual").unwrapped
    rig = EmulatedRig(env.embodiment, env.joints)
    try:
        twin = TwinInterface(env)
        twin.reset(seed=0)
        mirror = HardwareMirror(rig.config, env.embodiment, env.joints, env.model, env.control_hz)
        q = mirror.connect()
        np.testing.assert_allclose(q, env.joints.home, atol=2 * np.pi / 4096)
        twin.reset(seed=0, robot_qpos=q)
        mirror.start(twin.action)
        start = twin.action.copy()
        target = twin.action.copy()
        left0, right0 = twin.slices["left"].start, twin.slices["right"].start
        for _ in range(10):
            target[left0] += 0.02  # the left shoulder turns, slowly
            command = {n: JointCommand(n, target[sl], 0.0, 0.0) for n, sl in twin.slices.items()}
            state = twin.apply(command)
            mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
            time.sleep(1 / env.control_hz)
        # The twin's heartbeats (its last targets, once a period) until the left shoulder
        # measures where it was sent (read after its last write: up to a tick behind), however
        # long a busy machine takes to get there.
        deadline = time.monotonic() + 60.0
        measured = mirror.latest_measured()
        while abs(measured[left0] - target[left0]) >= 0.03 and time.monotonic() < deadline:
            state = twin.apply({})
            mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
            time.sleep(1 / env.control_hz)
            measured = mirror.latest_measured()
        mirror.close()
        summary = mirror.summary()
        assert set(summary) == {"left_arm", "left_hand", "right_arm", "right_hand"}
        assert all(d["errors"] == 0 and d["commands_sent"] >= 1 for d in summary.values())
        # The left shoulder followed; the right arm stayed home.
        assert abs(measured[left0] - target[left0]) < 0.03
        assert measured[left0] - env.joints.home[left0] > 0.15
        assert abs(measured[right0] - env.joints.home[right0]) < 1e-3
    finally:
        rig.close()
        env.close()
    # What the emulators received: the left arm's last target is the twin's, the right arm's
    # every target is where it started; both hands were written.
    left = np.array([q for _, q in rig.received["left_arm"]])
    right = np.array([q for _, q in rig.received["right_arm"]])
    sl = twin.slices["left"]
    np.testing.assert_allclose(left[-1], target[sl][:7], atol=1e-5)
    np.testing.assert_allclose(
        right, np.tile(start[right0 : right0 + 7], (len(right), 1)), atol=1e-5
    )
    assert rig.received["left_hand"] and rig.received["right_hand"]


def test_estop_from_keyboard_browser_and_headset_gesture():
    """Every e-stop input latches the mirror's e-stop and pauses the operator; the browser
    button and the keyboard release it and each shows the other's state."""
    import io
    from types import SimpleNamespace

    from beavr_sim.teleop.episodes import KeyboardControl
    from beavr_sim.teleop.mirroring import BrowserEstop, HeadsetEstop, MirrorFollower

    class FakeMirror:
        estopped = False
        submitted = 0
        failed_devices: list[str] = []

        def submit(self, *args):
            self.submitted += 1

        def estop(self, reason):
            self.estopped, self.reason = True, reason

        def release(self):
            self.estopped = False
            self.failed_devices = []  # (re-armed)

    class FakeOperator:
        paused = False
        gestures = ["estop"]

        def take_gestures(self, *kinds):
            taken = [g for g in self.gestures if g in kinds]
            self.gestures = [g for g in self.gestures if g not in kinds]
            return taken

        def set_paused(self, paused):
            self.paused = paused

    mirror, operator = FakeMirror(), FakeOperator()
    stage = SimpleNamespace(action=np.zeros(23), after_command=[], after_step=[], after_reset=[])
    MirrorFollower(stage, mirror)
    listener = HeadsetEstop(mirror, operator)
    state = SimpleNamespace(action=None, positions=None, guard_blocked_effectors=())
    tick = SimpleNamespace(state=state)
    (heartbeat,) = stage.after_step
    heartbeat(state)  # a step without a command: the mirror's heartbeat
    listener(tick)  # the headset gesture
    assert mirror.estopped and "headset" in mirror.reason and operator.paused
    view = SimpleNamespace(estop_requested=False)
    view.set_estop = lambda latched: setattr(view, "estop_requested", latched)
    browser = BrowserEstop(view, mirror)
    browser(tick)
    assert view.estop_requested  # the button shows the latched e-stop
    view.estop_requested = False  # clicked: release
    browser(tick)
    heartbeat(state)
    listener(tick)
    assert not mirror.estopped and not operator.paused
    view.estop_requested = True  # clicked: latch
    browser(tick)
    assert mirror.estopped and mirror.reason == "browser view"
    keyboard = KeyboardControl(None, io.StringIO("r\n"), actions={"r": ("release", mirror.release)})
    keyboard._thread.join(2.0)
    assert not mirror.estopped
    browser(tick)
    assert not view.estop_requested  # the keyboard's release shows on the button
    assert mirror.submitted == 2
    # A failed device shows as latched; the button's release re-arms it.
    mirror.failed_devices = ["right_hand"]
    browser(tick)
    assert view.estop_requested and not mirror.estopped
    view.estop_requested = False  # clicked: release
    browser(tick)
    assert mirror.failed_devices == [] and not mirror.estopped
    browser(tick)
    assert not view.estop_requested


def _rig_toml(rig_config: RigConfig, path) -> None:
    """A rig file for ``rig_config``'s emulated devices (their addresses and ports)."""
    lines = []
    for d in rig_config.devices:
        lines += ["[[devices]]", f'name = "{d.name}"', f'kind = "{d.kind}"']
        lines.append(f'effector = "{d.effector}"')
        if d.kind == "xarm7":
            lines += [f'host = "{d.config.host}"', f"port = {d.config.port}"]
            lines.append(f"max_joint_speed = {d.config.max_joint_speed}")
        else:
            lines += [f'port = "{d.config.port}"', "reply_timeout_s = 0.25"]
    lines += ["[mirror]", "hand_divergence_rad = 2.5"]
    path.write_text("\n".join(lines) + "\n")


def test_killing_the_operator_process_leaves_the_hardware_holding(tmp_path):
    """--multiprocess with mirroring: the operator process is killed mid-motion; the twin
    holds its last targets and so does the hardware (no new goals, or goals equal to the
    last), and the summary says the operator died."""
    from beavr_sim.hardware.rig import EmulatedRig
    from beavr_sim.teleop.processes import MultiprocessSession
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    rig = EmulatedRig(env.embodiment, env.joints)
    env.close()
    try:
        _rig_toml(rig.config, tmp_path / "rig.toml")
        options = SessionOptions(
            task="pickup_box",
            source="trace",
            viser=False,
            headless=True,
            multiprocess=True,
            mirror_hardware=True,
            hardware_config=str(tmp_path / "rig.toml"),
            transport=TransportConfig(ports=PortConfig.free()),
        )
        session = MultiprocessSession(options)
        session.start()
        try:
            # Until the twin reaches for the box (its arm 0.1 rad from where it started).
            start = _twin_state(session, lambda s: True)
            _twin_state(session, lambda s: _arm_moved(s, start) > 0.1)
            session.processes["operator"].kill()
            t_kill = time.monotonic()
            session.processes["operator"].join(30.0)
            # The commands in flight are taken within half a second of the twin's time; its
            # last targets then stand for another second of it.
            killed = _twin_state(session, lambda s: True)
            held = _twin_state(session, lambda s: s.t >= killed.t + 0.5)
            t_held = time.monotonic()
            _twin_state(session, lambda s: s.t >= held.t + 1.0)
        finally:
            session.stop()
        twin = session.results["twin"]
    finally:
        rig.close()
    assert twin["hardware"]["right_arm"]["errors"] == 0
    for name in ("right_arm", "right_hand"):
        log = rig.received[name]
        before = [targets for t, targets in log if t < t_kill]
        after = [targets for t, targets in log if t > t_held]
        assert before and after, name
        if name == "right_arm":
            moved = np.abs(np.array(before[-1]) - np.array(before[0])).max()
            assert moved > 0.05  # it was moving when the operator died
            assert all(np.allclose(q, after[0], atol=1e-6) for q in after)
        else:
            assert all(g == after[0] for g in after), name


def _twin_state(session, condition, timeout_s: float = 120.0):
    """The twin's first published state that meets ``condition`` (waits on the state stream:
    a busy machine slows the twin down, it does not make the test skip the wait)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = session.state_sub.recv_latest(0.5)
        if state is not None and condition(state):
            return state
    raise AssertionError(f"no twin state of the wanted kind within {timeout_s:.0f} s")


def _arm_moved(state, start) -> float:
    return float(np.abs(np.subtract(state.positions[:7], start.positions[:7])).max())


@pytest.mark.parametrize("multiprocess", [False, True])
def test_cli_refuses_to_start_naming_the_unreachable_device(tmp_path, capsys, multiprocess):
    dead = XArmEmulator()
    port = dead.port
    dead.close()
    rig = tmp_path / "rig.toml"
    rig.write_text(
        f'[[devices]]\nname = "right_arm"\nkind = "xarm7"\neffector = "right"\n'
        f'host = "127.0.0.1"\nport = {port}\nconnect_timeout_s = 1.0\n'
    )
    argv = ["--task", "pickup_box", "--source", "trace", "--no-viser", "--headless", "--quiet"]
    argv += ["--mirror-hardware", "--hardware-config", str(rig)]
    code = teleop_main(argv + (["--multiprocess"] if multiprocess else []))
    err = capsys.readouterr().err
    assert code == 3
    assert "cannot start mirroring: right_arm" in err and str(port) in err
    if multiprocess:  # the processes of the failed start are all ended, none left running
        assert [p.name for p in multiprocessing.active_children()] == []


def test_dry_run_connects_and_reads_but_never_writes():
    bench = Bench(dry_run=True)
    try:
        n_servo, n_goals = len(bench.arm.servo_log), len(bench.hand.goal_log)
        target = bench.twin.action.copy()
        for _ in range(5):
            target[0] += 0.03
            bench.step(target)
        assert len(bench.arm.servo_log) == n_servo and len(bench.hand.goal_log) == n_goals
        summary = bench.mirror.summary()
        assert summary["right_arm"]["connected"] and summary["right_arm"]["commands_sent"] == 0
        assert summary["right_arm"]["write_latency_ms"]["n"] == 5  # the dispatch still ran
    finally:
        bench.close()
    # Closing a dry run holds nothing either.
    assert len(bench.arm.servo_log) == n_servo


# ---------------------------------------------------------------- event-driven submits
@pytest.fixture
def clocked():
    clock = FakeClock()
    # The twin is where the devices are sent (its positions are the submitted actions) but
    # for catching up, where the devices trail it by design: no divergence hold then.
    b = Bench(MirrorConfig(arm_divergence_rad=1.0, hand_divergence_rad=2.5), clock=clock)
    b.submit_at(clock, 1 / 30, b.twin.action)  # the first submit (it stands for a period)
    yield b, clock
    b.close()


def test_submits_at_90_hz_are_each_written_as_submitted(clocked):
    bench, clock = clocked
    n_arm, n_hand = len(bench.arm_targets()), len(bench.hand_goals())
    target = bench.twin.action.copy()
    submitted = []
    for _ in range(12):  # 1.8 rad/s on an arm joint, 2.7 rad/s on a finger: within the caps
        target[0] += 0.02
        target[12] += 0.03
        submitted.append(bench.submit_at(clock, 1 / 90, target))
        np.testing.assert_array_equal(submitted[-1], target)  # nothing limited
    submitted = np.array(submitted)
    arm, hand = bench.arm_targets()[n_arm:], bench.hand_goals()[n_hand:]
    # One streamed step per command (90 Hz commands, a 100 Hz stream): written at once.
    np.testing.assert_allclose(arm, submitted[:, :7], atol=1e-5)
    np.testing.assert_allclose(hand, submitted[:, 7:], atol=np.pi / 4096 + 1e-9)
    for name, s in bench.mirror.summary().items():
        assert s["catch_up_steps"] == s["rate_limited"] == 0, name
        assert s["superseded"] == s["preempted"] == s["errors"] == 0, name
        assert s["write_latency_ms"]["n"] == 1 + 12, name  # (the fixture's first submit)


def test_bunched_submits_are_slowed_to_the_speed_cap(clocked):
    bench, clock = clocked
    mirror = bench.mirror
    vmax = np.array(mirror.speeds.reach.max_velocity)
    n_arm = len(bench.arm_targets())
    target = bench.twin.action.copy()
    times, dispatched = [clock()], [target.copy()]
    # A step fine over 11 ms (1.8 rad/s) but not over 0.5 ms (40 rad/s).
    for dt in (1 / 90, 0.0005):
        target[0] += 0.02
        dispatched.append(bench.submit_at(clock, dt, target))
        times.append(clock())
    # The second: 1 ms (the floor) of motion at the cap, not the whole step.
    assert dispatched[-1][0] - dispatched[-2][0] == pytest.approx(vmax[0] * 1e-3, rel=1e-9)
    assert mirror.summary()["right_arm"]["rate_limited"] == 1
    # The twin moves on at nearly its top speed: the mirror pays back what it owes at the
    # cap, never mistaking it for a jump (no slow catch-up).
    for _ in range(8):
        target[0] += 0.9 * vmax[0] / 90
        dispatched.append(bench.submit_at(clock, 1 / 90, target))
        times.append(clock())
    dispatched.append(bench.submit_at(clock, 1 / 90, target))
    times.append(clock())
    np.testing.assert_array_equal(dispatched[-1], target)  # caught up at the speed cap
    summary = mirror.summary()["right_arm"]
    assert summary["catch_up_steps"] == 0 and summary["rate_limited"] >= 2
    assert summary["superseded"] == 0
    # No joint moved faster than its cap between consecutive targets, over their submits'
    # spacing (floored); each was written (the stream's steps between them: at most 90 % of
    # the xArm's own cap per 10 ms step).
    written = bench.arm_targets()[n_arm:]
    dispatched, times = np.array(dispatched), np.array(times)
    steps = np.abs(np.diff(dispatched, axis=0))
    allowed = vmax * np.maximum(np.diff(times), 1e-3)[:, None]
    assert (steps <= allowed * (1 + 1e-9)).all()
    if summary["preempted"] == 0:  # (else a target is passed by on a loaded machine)
        for q in dispatched[1:, :7]:
            assert np.abs(written - q).max(axis=1).min() < 1e-5
    assert np.abs(np.diff(written, axis=0)).max() <= 0.9 * np.pi / 100 + 1e-5


def test_catch_up_speed_is_the_same_at_any_submit_rate(clocked):
    bench, clock = clocked
    mirror = bench.mirror
    home = bench.twin.action.copy()
    far = home.copy()
    far[0] += 0.5  # the twin jumped (a reset) while the devices held
    speed = mirror.rig.mirror.arm_catch_up_speed
    progress = {}
    for hz in (90, 30):
        mirror.estop("test")
        wait_for(lambda: mirror.summary()["right_arm"]["reason"] == "estop")
        mirror.release()
        start = mirror.links[0].last[0]  # where the arm holds
        t0 = clock()
        for _ in range(round(0.2 * hz)):  # 0.2 s of submits
            q = bench.submit_at(clock, 1 / hz, far)
        assert abs(bench.arm_targets()[-1][0] - q[0]) < 1e-5  # written
        progress[hz] = (q[0] - start) / (clock() - t0)
    assert progress[90] == pytest.approx(speed, rel=1e-4)
    assert progress[30] == pytest.approx(speed, rel=1e-4)
    summary = mirror.summary()["right_arm"]
    assert summary["catch_up_steps"] == 18 + 6 and summary["rate_limited"] == 0


def test_a_newer_target_preempts_a_streamed_interpolation(clocked):
    bench, clock = clocked
    home = bench.twin.action.copy()
    first = home.copy()
    first[0] += 0.09  # 30 Hz: streamed in 4 steps at 100 Hz (the xArm's cap: 90 % of pi)
    n_arm = len(bench.arm_targets())
    bench.submit_at(clock, 1 / 30, first, settle=False)
    wait_for(lambda: len(bench.arm.servo_log) > n_arm, poll_s=0.0002)  # its first step is out
    second = first.copy()
    second[2] += 0.02  # 11 ms later, another joint moves too
    bench.submit_at(clock, 1 / 90, second)
    arm = bench.arm_targets()[n_arm:]
    np.testing.assert_allclose(arm[0], home[:7] + (first - home)[:7] / 4, atol=1e-5)
    # The old stream's remaining steps (joint 3 still) were not all sent: never its end.
    old = [q for q in arm[1:] if abs(q[2] - home[2]) < 1e-6]
    assert len(old) < 3
    assert not any(np.allclose(q, first[:7], atol=1e-5) for q in arm)
    np.testing.assert_allclose(arm[-1], second[:7], atol=1e-5)
    summary = bench.mirror.summary()["right_arm"]
    assert summary["preempted"] == 1 and summary["superseded"] == 0
    assert summary["write_latency_ms"]["n"] == 1 + 2  # both targets written, each once taken


def test_a_device_whose_target_did_not_change_is_not_written_again(clocked):
    """A command for one device (the arm) leaves the other's target (the hand's) as it was:
    the hand is not written again within a control period, although the Dynamixel driver
    sends its targets quantized to encoder counts (never equal to the float target)."""
    bench, clock = clocked
    target = bench.twin.action.copy()
    target[7:] += 0.3 * RAD_PER_COUNT  # off the encoder's grid (the twin's targets are)
    bench.submit_at(clock, 1 / 90, target)
    sent = bench.mirror.links[1].last
    assert np.abs(sent - target[7:]).max() > 0.1 * RAD_PER_COUNT  # quantized when sent
    before = bench.mirror.summary()["right_hand"]
    arm_unchanged_before = bench.mirror.summary()["right_arm"]["unchanged"]
    n_goals = len(bench.hand_goals())
    for _ in range(12):
        target[0] += 0.02  # the arm moves, the hand's 16 targets stay
        bench.submit_at(clock, 1 / 90, target, settle=False)
        time.sleep(0.001)
    bench.wait_written()
    hand = bench.mirror.summary()["right_hand"]
    written = hand["write_latency_ms"]["n"] - before["write_latency_ms"]["n"]
    unchanged = hand["unchanged"] - before["unchanged"]
    superseded = hand["superseded"] - before["superseded"]
    assert written + unchanged + superseded == 12
    # At most one write per control period (its heartbeat) however fast the commands come.
    assert unchanged >= 6, hand
    assert len(bench.hand_goals()) - n_goals == written
    arm = bench.mirror.summary()["right_arm"]
    # The arm's target changed every time: each of the 12 was written (or superseded).
    assert abs(bench.arm_targets()[-1][0] - target[0]) < 1e-5
    assert arm["unchanged"] == arm_unchanged_before


# ------------------------------------------------------------------ the writers' port


def test_a_writer_reaches_the_mirror_only_through_its_port():
    """``link.py`` touches no lock and no private field of another object: every attribute
    it reads or writes with a leading underscore is its own (``self._x``), and it names no
    lock (``cond``) at all."""
    import ast
    from pathlib import Path

    import beavr_sim.hardware.mirror.link as link_module

    tree = ast.parse(Path(link_module.__file__).read_text())
    found = [
        f"{node.lineno}: {ast.unparse(node)}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and (
            node.attr in ("cond", "_cond")
            or (
                node.attr.startswith("_")
                and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id == "self")
            )
        )
    ]
    assert not found, found


def test_a_divergence_judged_before_a_release_does_not_latch():
    """A writer's reading judged against a divergence timer started before the operator's
    release (or a new episode) is not a hold: the port drops its latch; one judged after it
    latches and is a fault of the episode."""
    from beavr_sim.hardware.mirror.board import MirrorBoard
    from beavr_sim.hardware.mirror.divergence import Judgement

    board = MirrorBoard(["right_arm"], np.zeros(7), 1 / 30)
    port = board.port(0, MirrorConfig(), dry_run=True)
    judged = Judgement(0.4, "right/joint3", "diverged: right/joint3 0.400 rad for 0.60 s")
    with board.cond:
        board.devices[0].releases += 1  # released since the writer last took its orders
    port.judged(judged, releases=0)
    assert board.devices[0].latched == "" and board.faults == []
    assert board.devices[0].stats.max_divergence_rad == pytest.approx(0.4)  # still kept
    port.judged(judged, releases=1)
    assert board.devices[0].latched.startswith("diverged")
    assert board.faults == ["right_arm diverged: right/joint3 0.400 rad for 0.60 s"]
    assert board.orders(0).latched and board.halt_for(0) is None
