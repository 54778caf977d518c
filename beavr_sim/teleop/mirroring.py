"""Glue between the runners and the hardware mirror: connecting a rig for a session, the one
follower that hands the twin's guarded actions to the mirror (:class:`MirrorFollower`, on a
twin stage's hooks), the sync of a rig to an episode's start (:class:`RigSync`), and the
e-stop inputs (browser button, headset gesture) that latch it. Used by the single-process
session, the multiprocess twin and the LeRobot robot plugin.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from beavr_sim.datasets.recorder import FollowLimits, HardwareWatch
from beavr_sim.hardware.faults import parse_fault_specs
from beavr_sim.wire.records import Tick, TwinState

if TYPE_CHECKING:  # typing only: the stages import the operator (mink), heavy for the plugins
    from beavr_sim.teleop.stages import TwinStage
    from beavr_sim.twin.twin import CommandOutcome

#: Python's thread switch interval (s) in a process that mirrors: the mirror's writer threads
#: take the interpreter from the physics within this much, not the default 5 ms (a write
#: waits for the interpreter, not for a physics step).
MIRROR_SWITCH_INTERVAL_S = 0.0005


@dataclass(frozen=True)
class RigChoice:
    """Which rig a session mirrors to: a rig file (TOML) or ``"emulated"``, whether to write
    to it (``dry_run``: everything but the final write), and for the emulated rig the faults
    to rehearse (``--emulate-faults`` text, :mod:`beavr_sim.hardware.faults`)."""

    hardware_config: str
    dry_run: bool = False
    emulate_faults: str | None = None

    def __post_init__(self) -> None:
        if self.emulate_faults and self.hardware_config != "emulated":
            raise ValueError(
                "--emulate-faults needs --hardware-config emulated (faults are rehearsed on "
                f"the protocol emulators, not on {self.hardware_config})"
            )

    @classmethod
    def of(cls, options) -> RigChoice:
        """The choice of any options object with ``hardware_config`` and ``dry_run`` (and
        optionally ``emulate_faults``): :class:`SessionOptions`, a twin process's config."""
        return cls(
            str(options.hardware_config),
            bool(options.dry_run),
            getattr(options, "emulate_faults", None),
        )


def connect_mirror(choice: RigChoice, env, closers: list):
    """The rig of ``choice`` connected to the env's embodiment; returns the mirror and the
    measured joints (the twin starts there). Adds what must be closed to ``closers``. Raises
    :class:`~beavr_sim.hardware.device.MirrorError` (or ValueError, FileNotFoundError for the
    rig file or a bad fault spec) naming what to check."""
    from beavr_sim.hardware.mirror import HardwareMirror  # local: heavy (the pipeline: mink, scipy)
    from beavr_sim.hardware.rig import (  # local: heavy (mujoco)
        EmulatedRig,
        RigConfig,
        emulated_device_names,
    )

    if choice.hardware_config == "emulated":
        # Checked before any emulator starts: a bad spec names its part and the choices.
        faults = parse_fault_specs(
            choice.emulate_faults or "", emulated_device_names(env.embodiment)
        )
        rig = EmulatedRig(
            env.embodiment,
            env.joints,
            env.joints.home,
            env.hand_variant,
            faults=faults,
            keep_received=False,  # a session reads back the fault counts only
        )
        closers.append(rig.close)
        config = rig.config
        if faults:
            print(f"emulated faults: {', '.join(str(f) for f in faults)}", file=sys.stderr)
    else:
        config = RigConfig.from_toml(choice.hardware_config)
    variant = config.leap_variant()
    if variant is not None and variant != env.hand_variant:
        raise ValueError(
            f"the rig's LEAP hands are {variant!r} but the twin's are {env.hand_variant!r}: "
            "the twin must simulate the rig's hands (--leap-variant follows the rig)"
        )
    mirror = HardwareMirror(
        config, env.embodiment, env.joints, env.model, env.control_hz, dry_run=choice.dry_run
    )
    q_measured = mirror.connect()
    closers.append(mirror.close)
    print(
        f"mirroring {', '.join(link.name for link in mirror.links)}"
        f"{' (dry run: nothing is written)' if choice.dry_run else ''}",
        file=sys.stderr,
    )
    return mirror, q_measured


#: Per-device summary fields that describe device writes: left out of a dry run's summary
#: (nothing was written, so no write latency or rate exists).
WRITE_FIELDS = ("write_latency_ms", "write_rate_hz")


def hardware_summary(mirror) -> dict:
    """The mirror's per-device summary for the session's report; a dry run says so per
    device (``"dry_run": true``) and reports no write latency or rate."""
    out = mirror.summary()
    if mirror.dry_run:
        for stats in out.values():
            for name in WRITE_FIELDS:
                stats.pop(name, None)
            stats["dry_run"] = True
    return out


class MirrorFollower:
    """The hardware mirror follows a :class:`~beavr_sim.teleop.stages.TwinStage` through its
    hooks, the one wiring of every runner (the single-process loop, the multiprocess twin, the
    LeRobot robot plugin): each command the twin writes (``after_command``: the guarded
    action, at once; real time: one per hand frame), after a physics step without one
    (``after_step``) the same targets again (the mirror's heartbeat), each with the twin's
    joints after its last step; a new episode (``after_reset``, or :meth:`reset` for a runner
    that resets the twin itself) starts those joints over. Telling the mirror the episode's
    start and fixtures (``begin_episode``) is the runner's: a sync
    (:class:`RigSync`) or the robot plugin's reset.

    ``positions``: the twin's joints now (default: its action, as after a reset). Its hooks
    come first on the stage (the devices get each target before anything else runs) and are
    named ``mirror`` in the stage's hook errors."""

    def __init__(self, stage: TwinStage, mirror, positions: np.ndarray | None = None):
        self.stage, self.mirror = stage, mirror
        self._positions = np.array(
            stage.action if positions is None else positions, dtype=np.float64
        )
        self._submitted = False  # since the last step

        def mirror_command(outcome: CommandOutcome, commands) -> None:
            self.on_command(outcome)

        def mirror_step(state: TwinState) -> None:
            self.on_step(state)

        def mirror_reset(q: np.ndarray) -> None:
            self.reset(q)

        for hook in (mirror_command, mirror_step, mirror_reset):
            hook.__name__ = "mirror"
        stage.after_command.insert(0, mirror_command)
        stage.after_step.insert(0, mirror_step)
        stage.after_reset.insert(0, mirror_reset)

    def on_command(self, outcome: CommandOutcome) -> None:
        """The twin wrote a command: its guarded action goes to the mirror now."""
        self.mirror.submit(self.stage.action.copy(), self._positions, outcome.blocked)
        self._submitted = True

    def on_step(self, state: TwinState) -> None:
        """The physics stepped: without a command since the last step, the same targets
        (the heartbeat); the twin's joints are the step's from now on."""
        if not self._submitted:
            self.mirror.submit(state.action, state.positions, state.guard_blocked_effectors)
        self._submitted = False
        self._positions = state.positions

    def reset(self, q: np.ndarray) -> None:
        """A new episode: the twin's joints are ``q`` (action order)."""
        self._positions = np.array(q, dtype=np.float64)


class HeadsetEstop:
    """The single-process loop's tick listener for the headset's e-stop gesture (both hands
    pinch): it latches the mirror's e-stop, and while the e-stop is latched (from any input)
    the operator is paused, so nothing jumps at release. (The multiprocess twin gets the
    gesture as an operator event and pauses its commands itself.)"""

    def __init__(self, mirror, operator):
        self.mirror, self.operator = mirror, operator
        self._estopped = False

    def __call__(self, tick: Tick) -> None:
        if self.operator.take_gestures("estop"):
            self.mirror.estop("headset gesture: both hands pinch")
        if self.mirror.estopped != self._estopped:
            self._estopped = self.mirror.estopped
            self.operator.set_paused(self._estopped)


def episode_fault(mirror) -> str:
    """The mirror's first fault of the episode ("" when none): what a run's line reports."""
    health = mirror.health()
    faults = tuple(health.episode_faults)
    if faults:
        return faults[0]
    failed = list(mirror.failed_devices)
    return f"{', '.join(failed)} failed" if failed else ""


def failed_for_good(mirror) -> list[str]:
    """Devices that failed and stay out until re-armed (``FAILED``; a device in an outage
    is still being reconnected and may come back by itself)."""
    return [d.name for d in mirror.health().devices if d.state.name == "FAILED"]


class RigSync:
    """Whether a mirrored rig reached an episode's start pose: :meth:`begin` tells the mirror
    the twin's start (its guarded catch-up brings every device there), then :meth:`poll`
    (once per tick) says when the rig is in sync, or why it will not be: a device failed and
    nobody can re-arm it (not ``interactive``), or ``timeout_s`` (wall) passed. The one
    sync of both layouts: the session's :class:`~beavr_sim.teleop.session.HardwareSync` and
    the multiprocess twin."""

    def __init__(
        self,
        mirror,
        timeout_s: float,
        interactive: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ):
        if not 0 < timeout_s < float("inf"):
            raise ValueError(f"sync timeout must be positive, got {timeout_s}")
        self.mirror = mirror
        self.timeout_s = float(timeout_s)
        self.interactive = interactive
        self.clock = clock
        self.syncing = False
        #: Why the last sync did not complete ("" when it did, or none ran).
        self.fault = ""
        #: Completed syncs, and how long (wall s) the last one took (or ran until its fault).
        self.synced = 0
        self.last_sync_s = 0.0
        self._started = 0.0
        self._deadline = 0.0

    def begin(self, action, fixtures) -> None:
        """The twin was just reset to the episode's start (``action``, ``fixtures``): the
        devices catch up with it from now on."""
        self.mirror.begin_episode(action, fixtures=fixtures)
        self.syncing = True
        self.fault = ""
        self._started = self.clock()
        self._deadline = self._started + self.timeout_s

    def poll(self) -> str | None:
        """None while syncing (or when no sync runs); once it ends: "" in sync (counted), or
        the fault."""
        if not self.syncing:
            return None
        if self.mirror.in_sync():
            self.synced += 1
            return self.end("")
        failed = failed_for_good(self.mirror)
        if failed and not self.interactive:
            return self.end(f"{', '.join(failed)} failed and was not re-armed: {self.why()}")
        if self.clock() > self._deadline:
            return self.end(
                f"the hardware did not reach the episode's start pose within "
                f"{self.timeout_s:g} s: {self.why()}"
            )
        return None

    def end(self, fault: str) -> str:
        """End the sync with ``fault`` ("" in sync); returns it."""
        self.syncing = False
        self.last_sync_s = self.clock() - self._started
        self.fault = fault
        return fault

    def why(self) -> str:
        """Which devices are not there and why, and the episode's last fault line."""
        health = self.mirror.health()
        parts = [
            f"{d.name} {d.state.name.lower()}" + (f" ({d.detail})" if d.detail else "")
            for d in health.devices
            if d.state.name != "FOLLOWING"
        ] or ["every device follows, but not yet within the sync tolerance of the twin"]
        faults = tuple(health.episode_faults)
        if faults:
            parts.append(f"last fault: {faults[-1]}")
        return "; ".join(parts)


class BrowserEstop:
    """Keeps the browser view's emergency-stop button and the mirror in step: the button
    latches the e-stop, and its release releases it and re-arms failed devices
    (:meth:`~beavr_sim.hardware.mirror.HardwareMirror.release`); the button shows latched while
    the e-stop is latched (from any input) or a device is failed, so a failed rig is re-armed
    from the browser the way an e-stop is released."""

    def __init__(self, view, mirror):
        self.view, self.mirror = view, mirror
        self._shown = False

    def _held(self) -> bool:
        return bool(self.mirror.estopped or self.mirror.failed_devices)

    def __call__(self, tick: Tick) -> None:
        if self.view.estop_requested != self._shown:  # the button was clicked
            self._shown = self.view.estop_requested
            if self._shown:
                self.mirror.estop("browser view")
            else:
                self.mirror.release()  # (re-arms a failed device, without waiting)
        elif self._held() != self._shown:  # latched, failed, released or re-armed elsewhere
            self._shown = self._held()
            self.view.set_estop(self._shown)


def follow_limits(mirror, env):
    """The rig's divergence limits per joint of the action (``inf`` where no device measures
    a joint) and its window: what the recorder holds the measured state to."""

    limit = np.full(env.joints.size, np.inf)
    for link in mirror.links:
        limit[link.index] = link.divergence_limit
    return FollowLimits(
        limit_rad=limit,
        window_s=float(mirror.rig.mirror.divergence_window_s),
        joint_names=tuple(env.joints.names),
        lag_s=float(mirror.rig.mirror.device_lag_s),
    )


def hardware_watch(mirror, env, fps: float) -> HardwareWatch:
    """The recorder's per-frame check of a mirrored rig's measured state (both layouts')."""
    return HardwareWatch(mirror.latest_reading, mirror.health, follow_limits(mirror, env), fps)
