"""Hardware mirroring, event-driven: every guarded command the twin applies goes to the devices.

The twin's thread calls :meth:`HardwareMirror.submit` with each action the moment it applies
it (already past the guard, :mod:`beavr_sim.twin.guard`): once per guarded command (one per
hand frame, at the headset's rate, with its jitter), and once per control period when no
command came in that period (a heartbeat with the same targets); with the twin's measured
joints. Each device has its own writer thread (a slow serial bus never slows the twin) that
sends the newest target and reads the measured joints back. The mirror:

- sends only what the twin's guard accepted: a command the twin refused never reaches a motor
  (the twin holds that effector, and so the device holds);
- limits every target it sends to the device's speed (:class:`~beavr_sim.twin.guard.GuardConfig`
  caps, :mod:`~beavr_sim.hardware.mirror.speed`) over the time since the previous submit (at
  most one control period, at least :data:`~beavr_sim.hardware.mirror.speed.MIN_INTERVAL_S`):
  commands bunched by scheduling jitter are slowed to the speed cap (``rate_limited``); when
  the twin is further away than one period's motion (after a hold, a release, a reset:
  :meth:`begin_episode`) the device *catches up* at the slower catch-up speed, whatever the
  submit rate, each intermediate target checked by the mirror's own copy of the guard (told
  each episode's fixtures) along its path (:mod:`~beavr_sim.hardware.mirror.catch_up`);
- streams a device that wants a stream (:attr:`~beavr_sim.hardware.device.Device.stream_hz`)
  each target interpolated from the last one sent over the time that target stands for; a
  newer target ends the interpolation and goes out at once from where the device was last
  sent; a target superseded before its first write is never written (``superseded``);
- judges each device against what it was asked to do
  (:mod:`~beavr_sim.hardware.mirror.divergence`): a device whose measured joints stay
  further than a threshold from every target it was sent within its lag
  (:attr:`~beavr_sim.hardware.rig.MirrorConfig.device_lag_s`) for longer than a window holds
  (latched until :meth:`release` or the next :meth:`begin_episode`); a catch-up is judged the
  same way, so a reset never latches a hold;
- holds every device when no fresh command came within a timeout (a stalled twin, the pause
  between episodes): a hold that resumes, catching up, when commands come again;
- latches an emergency stop (:meth:`estop`) that holds every device until :meth:`release`;
- rides out a device that stops answering (a read or write raises
  :class:`~beavr_sim.hardware.device.DeviceError`): it is in ``OUTAGE`` and every other device
  holds; it is reconnected every
  :data:`~beavr_sim.hardware.mirror.link.RECONNECT_INTERVAL_S` for up to
  :attr:`~beavr_sim.hardware.rig.MirrorConfig.reconnect_s`; back in time and where it was held,
  it resumes through a guarded catch-up (``recovered``); otherwise it is ``FAILED`` (and the
  rest of the rig holds) until the operator re-arms it (:meth:`rearm`, also part of
  :meth:`release`);
- refuses to start when a device cannot be reached (:meth:`connect` names it and what to check).

Threads: the twin's thread (submit, health, in_sync), one writer per device, and the operator's
inputs (estop, release, rearm: keyboard, browser) share one lock, the
:class:`~beavr_sim.hardware.mirror.board.MirrorBoard`'s; every counter and every device state
is written under it. A writer reaches it only through its
:class:`~beavr_sim.hardware.mirror.board.LinkPort` and works from frozen
:class:`~beavr_sim.hardware.mirror.dispatch.Orders` snapshots. Device state is
a :class:`LinkState` plus a :class:`HoldReason` and a one-line detail for people (never
parsed). Statistics are bounded (a ring of the last writes).

Called once per control period it does what lockstep mirroring did (each step at most one
period's motion, catch-up at one period's catch-up step, streams over a whole period).
``dry_run`` does everything but the final write (the devices are connected and read).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from beavr_sim.hardware.detour import Detour
from beavr_sim.hardware.device import DeviceError, MirrorError
from beavr_sim.hardware.mirror.board import MirrorBoard
from beavr_sim.hardware.mirror.catch_up import CatchUp
from beavr_sim.hardware.mirror.dispatch import Dispatch
from beavr_sim.hardware.mirror.errors import log, one_line
from beavr_sim.hardware.mirror.link import Link
from beavr_sim.hardware.mirror.speed import MirrorSpeeds, submit_interval
from beavr_sim.hardware.mirror.state import (
    MOVING,
    OUT,
    DeviceHealth,
    Fixtures,
    HoldReason,
    LinkState,
    MirrorHealth,
    Reading,
)
from beavr_sim.hardware.rig import BODY, RigConfig, build_device, joint_names_of
from beavr_sim.robots.embodiment import Embodiment, JointIndex
from beavr_sim.twin.guard import CollisionGuard, GuardConfig

#: How long (s) :meth:`HardwareMirror.close` waits for a writer thread (one inside a reconnect
#: waits for its driver's connect timeout).
JOIN_TIMEOUT_S = 5.0


class HardwareMirror:
    """The devices of a rig following the twin's guarded commands (see the module docstring)."""

    def __init__(
        self,
        rig: RigConfig,
        embodiment: Embodiment,
        joints: JointIndex,
        model,
        control_hz: float,
        *,
        guard: GuardConfig | None = None,
        dry_run: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ):
        """``clock``: monotonic seconds, the time between submits is measured with (tests
        inject one)."""
        rig.check_embodiment(embodiment)
        self.rig = rig
        self.joints = joints
        self.dry_run = bool(dry_run)
        self._period = 1.0 / control_hz
        self._clock = clock
        guard_config = guard or GuardConfig()
        # The mirror's own guard checks the targets it makes itself (catching up).
        self.guard = CollisionGuard(model, embodiment, joints, guard_config, dt=self._period)
        built = []
        for entry in rig.devices:
            device = build_device(entry, embodiment, joints)
            index = np.array([joints.names.index(n) for n in joint_names_of(entry, embodiment)])
            built.append((device, index, entry.part))
        home = joints.home.astype(np.float64).copy()
        #: The one lock and everything shared under it (each writer gets its port).
        self._board = MirrorBoard([device.name for device, _, _ in built], home, self._period)
        board = self._board
        self.links: list[Link] = [
            Link(board.port(k, rig.mirror, self.dry_run), board.devices[k], device, index, part)
            for k, (device, index, part) in enumerate(built)
        ]
        effector_of = dict.fromkeys(embodiment.body_joints, BODY)  # the body: never refused
        for e in embodiment.effectors:
            for n in e.joints:
                effector_of[n] = e.name
        self._link_effector = [effector_of[joints.names[link.index[0]]] for link in self.links]
        #: Every speed cap the mirror sends with (:mod:`~beavr_sim.hardware.mirror.speed`).
        self.speeds = MirrorSpeeds.of(
            self.guard.max_velocity,
            [(link.index, link.device.max_velocity) for link in self.links],
            self.guard.hand_joints,
            rig.mirror,
        )
        #: Per action index, the speed (rad/s) the rig follows (the guard's cap, no faster than
        #: a device's own): the twin steps no faster (``TwinInterface.follow_speed_caps``).
        self.speed_caps = self.speeds.caps.copy()
        qpos = np.zeros(model.nq)
        qpos[joints.qpos_adr] = joints.home
        #: The guarded catch-up (and its detours), the twin's thread only.
        self.catch_up = CatchUp(self.guard, self.speeds.catch_up, qpos)
        #: The time (``clock``) of the previous submit (none yet: the first stands for a whole
        #: period).
        self._t_previous = -math.inf
        #: What the last submit left of its action because of the rate limit (action - target;
        #: zero after a catch-up): distance the mirror still owes, not a jump of the twin.
        self._owed = np.zeros(joints.size)
        self._episodes = 0
        #: The last dispatch before the episode began: in sync needs reads after it.
        self._begin_seq = 0
        self._catch_up_refusals = 0  # (the twin's thread only)
        self.started = False

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> np.ndarray:
        """Connect every device; returns the measured joints in action order (the twin starts
        there). Raises :class:`MirrorError` naming the device and what to check; devices
        already connected are released."""
        for link in self.links:
            try:
                link.device.connect()
            except (DeviceError, OSError, ValueError) as exc:
                self.close()
                raise MirrorError(f"cannot start mirroring: {link.name}: {exc}") from None
            with self._board.cond:
                link.shared.stats.connected = link.shared.stats.connected_now = True
        return self.measured()

    def measured(self) -> np.ndarray:
        """Measured joints of every device, in action order (home where no device); read
        now (before :meth:`start`: the writers read them afterwards)."""
        q = self.joints.home.astype(np.float64).copy()
        for link in self.links:
            measured = np.asarray(link.device.read_positions(), dtype=np.float64)
            now = time.monotonic()
            with self._board.cond:
                link.shared.measured = measured
                link.shared.measured_t = now
            q[link.index] = measured
        return q

    def latest_measured(self) -> np.ndarray:
        """The devices' joints as their writer threads last read them (action order; the
        last dispatched target where a device has not been read yet)."""
        return self.latest_reading().q

    def latest_reading(self) -> Reading:
        """:meth:`latest_measured`, and when its oldest device reading was taken (one lock:
        the joints and their time belong together)."""
        with self._board.cond:
            q = self._board.dispatch.target.copy()
            t_oldest, oldest = math.inf, ""
            for link in self.links:
                shared = link.shared
                if shared.measured is not None:
                    q[link.index] = shared.measured
                if shared.measured_t < t_oldest:
                    t_oldest, oldest = shared.measured_t, shared.name
        return Reading(q, t_oldest if self.links else time.monotonic(), oldest)

    def start(self, q_start: np.ndarray) -> None:
        """Start following from ``q_start`` (the measured pose the twin was reset to)."""
        q = np.asarray(q_start, dtype=np.float64).copy()
        with self._board.cond:
            self._board.dispatch = Dispatch(
                0, q, q.copy(), (False,) * len(self.links), 0.0, time.monotonic(), self._period
            )
            self._t_previous = -math.inf
            self._owed = np.zeros_like(q)
            for link in self.links:
                link.shared.last = q[link.index].copy()
                link.restart_from(link.shared.last)  # its writer has not started yet
        self.guard.reset()
        for link in self.links:
            link.start()
        self.started = True

    def begin_episode(self, q_start: np.ndarray, fixtures: Fixtures | None = None) -> None:
        """The twin was reset to ``q_start`` (action order) for a new episode.

        The mirror's guard is told this episode's ``fixtures`` (:meth:`Fixtures.of` the env's
        data after its reset) and forgets its motion history; a divergence hold is released
        and the episode's fault record cleared. The devices are then brought to ``q_start``
        by the guarded, speed-capped catch-up as the twin's submits (heartbeats while the
        operator is paused) come in; :meth:`in_sync` says when they are there. An e-stop
        stays latched and a failed device stays failed (:meth:`release`, :meth:`rearm`)."""
        q = np.asarray(q_start, dtype=np.float64)
        if q.shape != (self.joints.size,):
            raise ValueError(
                f"begin_episode: q_start has shape {q.shape}, not ({self.joints.size},)"
            )
        if fixtures is not None:
            self.guard.set_fixtures(fixtures.mocap_pos, fixtures.mocap_quat)
        self.guard.reset()
        self.catch_up.reset()
        board = self._board
        with board.cond:
            self._episodes += 1
            self._begin_seq = board.dispatch.seq
            board.faults.clear()
            self._owed = np.zeros_like(self._owed)
            for shared in board.devices:
                shared.latched = ""
                shared.releases += 1  # its divergence timer starts over
            board.cond.notify_all()

    def close(self) -> None:
        """Hold and release every device (idempotent)."""
        board = self._board
        board.stopping.set()
        with board.cond:
            board.cond.notify_all()
        for link in self.links:
            ended = link.join(JOIN_TIMEOUT_S)
            if not ended:
                log.error("%s: its writer did not stop (a reconnect hangs): left as is", link.name)
                continue
            shared = link.shared
            with board.cond:
                hold = shared.stats.connected_now and not self.dry_run and shared.state not in OUT
            if hold:
                try:
                    link.device.hold()
                except Exception as exc:  # closing: note it, go on
                    with board.cond:
                        shared.stats.errors += 1
                        shared.stats.last_error = one_line(exc)
            link.device.disconnect()
            with board.cond:
                shared.stats.connected_now = False

    # ------------------------------------------------------------------ per command
    def submit(
        self, action: np.ndarray, twin_positions: np.ndarray, refused: Sequence[str] = ()
    ) -> None:
        """The twin applied ``action`` (past its guard): a guarded command, or the period's
        heartbeat; its joints are ``twin_positions``; ``refused``: effectors whose command
        the guard refused."""
        if not self.started:
            raise RuntimeError("HardwareMirror.submit before start()")
        action = np.array(action, dtype=np.float64)  # a copy: the caller may reuse its array
        twin = np.array(twin_positions, dtype=np.float64)
        t = self._clock()
        dt = min(max(t - self._t_previous, 0.0), self._period)
        self._t_previous = t
        board = self._board
        with board.cond:
            previous = board.dispatch.target.copy()
            owed = self._owed.copy()
            for link in self.links:  # a device not following starts from where it stands
                if link.shared.anchor is not None:
                    previous[link.index] = link.shared.anchor
                    owed[link.index] = 0.0
        step = action - previous
        rate_limited: list[int] = []
        caught, catch_up_refused = False, False
        interval = submit_interval(dt)
        if self.speeds.reach.exceeds(step - owed, self._period).any():
            # The twin is further than one period of motion away (not counting what the rate
            # limit still owes): catch up slowly, at the same speed whatever the submit rate,
            # guarded.
            caught = True
            target, verdict = self.catch_up.step(action, previous, interval)
            if not verdict.ok:
                for name in verdict.blocked:
                    sl = self.joints.slices[name]
                    target[sl] = previous[sl]
                catch_up_refused = True
            owed_next = np.zeros_like(action)
        else:
            # Within a period's motion, but no faster than the speed cap over the time since
            # the last submit: a device's step is shortened along its direction (its target
            # stays on the line to the guarded action); the rest is owed, not a jump.
            limited = self.speeds.rate.clamp(previous, action, interval)
            target = limited.target
            rate_limited = [
                k for k, link in enumerate(self.links) if limited.limited[link.index].any()
            ]
            owed_next = action - target
        catching = tuple(
            bool(caught and (target[link.index] != action[link.index]).any()) for link in self.links
        )
        if catch_up_refused:
            self._catch_up_refusals += 1
            n = self._catch_up_refusals
            if n in (1, 10, 100) or n % 1000 == 0:
                log.warning(
                    "mirror catch-up refused: %s (the devices hold those joints; %d so far)",
                    verdict.reason(),
                    n,
                )
        with board.cond:
            for k, shared in enumerate(board.devices):
                if catching[k]:
                    shared.stats.catch_up_steps += 1
                    shared.stats.catch_up_refused += catch_up_refused
                if k in rate_limited:
                    shared.stats.rate_limited += 1
                if self._link_effector[k] in refused:
                    shared.stats.commands_refused += 1
            self._owed = owed_next
            board.dispatch = Dispatch(
                board.dispatch.seq + 1,
                target,
                twin,
                catching,
                time.perf_counter(),
                time.monotonic(),
                dt,
            )
            board.cond.notify_all()

    @property
    def detours(self) -> list[Detour]:
        """Every detour the catch-up planned (found or not), oldest first."""
        return self.catch_up.detours

    @property
    def dispatched(self) -> Dispatch:
        """The newest dispatch (frozen: its targets are what the writers send)."""
        with self._board.cond:
            return self._board.dispatch

    # ------------------------------------------------------------------ safety
    def estop(self, reason: str = "emergency stop") -> None:
        """Hold every device now; latched until :meth:`release`."""
        board = self._board
        with board.cond:
            if not board.estop:
                board.fault(f"e-stop: {reason}")
            board.estop = reason or "emergency stop"
            board.cond.notify_all()
        log.error("EMERGENCY STOP (%s): every device holds until released", reason)

    def release(self) -> None:
        """Release the e-stop and any divergence hold, and re-arm failed devices (without
        waiting: see :meth:`rearm`); the devices catch up with the twin slowly."""
        board = self._board
        with board.cond:
            board.estop = ""
            for shared in board.devices:
                shared.latched = ""
                shared.releases += 1  # its divergence timer starts over
            board.cond.notify_all()
        if self.failed_devices:
            self.rearm(timeout_s=0.0)

    def rearm(self, timeout_s: float | None = None) -> list[str]:
        """Re-arm the failed devices (the operator checked them): each is reconnected and
        re-read by its writer and follows again from where it stands, through a guarded
        catch-up. Waits up to ``timeout_s`` (None: ``reconnect_s``) for the attempts; returns
        the devices still failed or in outage."""
        board = self._board
        with board.cond:
            for shared in board.devices:
                if shared.state is LinkState.FAILED:
                    shared.rearm_requested = True
            board.cond.notify_all()
            wait = self.rig.mirror.reconnect_s if timeout_s is None else timeout_s
            if wait > 0 and self.started:
                board.cond.wait_for(
                    lambda: not any(shared.rearm_requested for shared in board.devices),
                    timeout=wait,
                )
        return self.failed_devices

    @property
    def faults_total(self) -> int:
        """Faults (e-stops, divergences, outages, failures) over the whole session."""
        with self._board.cond:
            return self._board.faults_total

    @property
    def estopped(self) -> bool:
        with self._board.cond:
            return bool(self._board.estop)

    @property
    def failed_devices(self) -> list[str]:
        """Devices that failed (or are in outage) and are not recovered."""
        with self._board.cond:
            return [shared.name for shared in self._board.devices if shared.state in OUT]

    # ------------------------------------------------------------------ state
    def health(self) -> MirrorHealth:
        """Every device's state now (cheap: one lock, no device access)."""
        board = self._board
        with board.cond:
            fresh = time.monotonic() - board.dispatch.t_submit <= self.rig.mirror.command_timeout_s
            devices = tuple(
                DeviceHealth(d.name, d.state, d.reason, d.detail) for d in board.devices
            )
            live = not board.estop and all(
                not d.latched
                and (
                    d.state in MOVING
                    or (d.state is LinkState.HOLDING and d.reason is HoldReason.TIMEOUT and fresh)
                )
                for d in board.devices
            )
            return MirrorHealth(live, devices, tuple(board.faults))

    def in_sync(self) -> bool:
        """Every device following (not catching up, not held) and its measured joints, read
        since the episode began (:meth:`begin_episode`), within its part's sync tolerance of
        the twin's."""
        with self._board.cond:
            if self._board.estop:
                return False
            twin = self._board.dispatch.twin
            for link in self.links:
                shared = link.shared
                if (
                    shared.state is not LinkState.FOLLOWING
                    or shared.latched
                    or shared.measured is None
                    or shared.measured_seq <= self._begin_seq
                ):
                    return False
                gap = np.abs(shared.measured - twin[link.index])
                if float(np.max(gap, initial=0.0)) > link.sync_tolerance:
                    return False
            return True

    # ------------------------------------------------------------------ report
    def summary(self) -> dict:
        out = {}
        with self._board.cond:
            for link in self.links:
                shared = link.shared
                s = shared.stats.summary()
                s["state"] = shared.state.value
                s["reason"] = shared.reason.value
                s["holding"] = shared.detail if shared.state is not LinkState.FOLLOWING else ""
                s["retries"] = link.retries
                out[link.name] = s
        return out
