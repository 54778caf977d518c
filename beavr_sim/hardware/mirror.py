"""Hardware mirroring in lockstep: every guarded command the twin applies goes to the devices.

The twin's thread calls :meth:`HardwareMirror.submit` once per control tick with the action the
twin just applied (already past the guard, :mod:`beavr_sim.twin.guard`) and the twin's measured
joints. Each device has its own writer thread (a slow serial bus never slows the twin) that
sends the newest target and reads the measured joints back. The mirror:

- sends only what the twin's guard accepted: a command the twin refused never reaches a motor
  (the twin holds that effector, and so the device holds);
- limits every target it sends to the device's speed (:class:`~beavr_sim.twin.guard.GuardConfig`
  caps) from the last one sent; when the twin is further away than one tick's motion (after a
  hold, a release, a reset) the device *catches up* at the slower catch-up speed, each
  intermediate target checked by the mirror's own copy of the guard along its path;
- holds a device whose measured joints stay further than a threshold from the twin's for longer
  than a window, and every device when no fresh command came within a timeout (a dead operator
  or twin), saying why; resumes (catching up) when commands come again;
- latches an emergency stop (:meth:`estop`) that holds every device until :meth:`release`;
- holds every other device when one fails (a vanished serial port, a controller error), and
  refuses to start when a device cannot be reached (:meth:`connect` names it and what to check).

``dry_run`` does everything but the final write (the devices are connected and read).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.hardware.device import Device, DeviceError, MirrorError
from beavr_sim.hardware.rig import BODY, RigConfig, build_device, joint_names_of
from beavr_sim.robots.embodiment import Embodiment, JointIndex
from beavr_sim.twin.guard import CollisionGuard, GuardConfig

log = logging.getLogger(__name__)


@dataclass
class DeviceStats:
    connected: bool = False
    commands_sent: int = 0
    #: Ticks in which the twin's guard refused this device's effector (nothing was sent).
    commands_refused: int = 0
    #: Times the device was put on hold (timeout, divergence, e-stop, another device's failure).
    holds: int = 0
    max_divergence_rad: float = 0.0
    max_divergence_joint: str = ""
    errors: int = 0
    #: Why the device is holding now ("" while it follows the twin).
    holding: str = ""
    last_error: str = ""
    #: Targets limited to the catch-up speed.
    catch_up_steps: int = 0
    write_latency_ms: list[float] = field(default_factory=list)
    write_times: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        lat = np.asarray(self.write_latency_ms)
        return {
            "connected": self.connected,
            "commands_sent": self.commands_sent,
            "commands_refused": self.commands_refused,
            "holds": self.holds,
            "max_divergence_rad": round(self.max_divergence_rad, 4),
            "max_divergence_joint": self.max_divergence_joint,
            "errors": self.errors,
            "holding": self.holding,
            "last_error": self.last_error,
            "catch_up_steps": self.catch_up_steps,
            "write_latency_ms": {
                "p50": float(np.percentile(lat, 50)) if lat.size else None,
                "p99": float(np.percentile(lat, 99)) if lat.size else None,
                "n": int(lat.size),
            },
        }


class _Link:
    """One device, its joints in the action, and its writer thread."""

    def __init__(self, mirror: HardwareMirror, device: Device, index: np.ndarray, part: str):
        self.mirror = mirror
        self.device = device
        self.index = index
        config = mirror.rig.mirror
        self.divergence_limit = (
            config.hand_divergence_rad if part == "hand" else config.arm_divergence_rad
        )
        self.stats = DeviceStats()
        self._seq_sent = 0
        self._diverged_since: float | None = None
        self._held = False
        self._last: np.ndarray | None = None  # the last target sent
        #: The device's joints as last read by its writer thread.
        self.measured: np.ndarray | None = None
        self._thread: threading.Thread | None = None

    @property
    def name(self) -> str:
        return self.device.name

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"mirror-{self.name}", daemon=True)
        self._thread.start()

    def join(self, timeout: float) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _hold(self, why: str) -> None:
        if self.stats.holding != why:
            if not self.stats.holding:
                self.stats.holds += 1
            log.warning("%s holds: %s", self.name, why)
            self.stats.holding = why
        if not self._held:
            self._held = True
            if not self.mirror.dry_run:
                try:
                    self.device.hold()
                except DeviceError as exc:
                    self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        self.stats.errors += 1
        self.stats.last_error = str(exc)
        self.mirror._device_failed(self, exc)

    def _write(self, q: np.ndarray, t_dispatch: float, now: float) -> None:
        """Send ``q``; a device that wants a stream gets it interpolated from the last target
        over one control period, at its rate (the first step leaves at once)."""
        m = self.mirror
        steps = [q]
        rate = self.device.stream_hz
        if rate and self._last is not None:
            # One control period of steps at the device's rate, more if a step would pass
            # the device's own speed cap (90 % of it per step).
            n = max(1, round(m._period * rate))
            if self.device.max_velocity:
                largest = float(np.max(np.abs(q - self._last), initial=0.0))
                n = max(n, math.ceil(largest / (0.9 * self.device.max_velocity / rate)))
            steps = [self._last + (q - self._last) * (k / n) for k in range(1, n + 1)]
        start = time.perf_counter()
        for k, step in enumerate(steps):
            if k:
                time.sleep(max(0.0, start + k / rate - time.perf_counter()))
                if m._halted or m._stopping.is_set():
                    break  # a hold takes over from here
            if not m.dry_run:
                self._last = self.device.send_positions(step)
                self.stats.commands_sent += 1
            else:
                self._last = np.asarray(step, dtype=np.float64)
            if k == 0:
                self.stats.write_latency_ms.append((time.perf_counter() - t_dispatch) * 1e3)
                self.stats.write_times.append(now)
                self._held = False
                self.stats.holding = ""

    def _run(self) -> None:
        m = self.mirror
        while not m._stopping.is_set():
            with m._cond:
                m._cond.wait_for(
                    lambda: m._seq != self._seq_sent or m._stopping.is_set(), timeout=m._period
                )
                seq, target, t_dispatch = m._seq, m._dispatched, m._t_dispatch
                twin = m._twin_positions
                halted = m._halted
                t_submit = m._t_submit
            if m._stopping.is_set():
                break
            if self.stats.holding.startswith("failed"):
                continue
            now = time.monotonic()
            if halted:
                self._hold(halted)
                self._seq_sent = seq
                continue
            if self.stats.holding.startswith("diverged"):
                self._seq_sent = seq
                continue  # latched until a release
            if now - t_submit > m.rig.mirror.command_timeout_s:
                self._hold(f"no fresh command within {m.rig.mirror.command_timeout_s:g} s")
                continue
            if seq == self._seq_sent:
                continue
            self._seq_sent = seq
            q = target[self.index]
            try:
                self._write(q, t_dispatch, now)
                measured = self.device.read_positions()
                self.measured = measured
            except Exception as exc:  # a writer never dies silently: the device fails
                log.exception("%s: write failed", self.name)
                self._fail(exc if isinstance(exc, DeviceError) else DeviceError(repr(exc)))
                continue
            if m.dry_run:
                continue
            gap = np.abs(measured - twin[self.index])
            divergence = float(np.max(gap))
            if divergence > self.stats.max_divergence_rad:
                self.stats.max_divergence_rad = divergence
                self.stats.max_divergence_joint = self.device.joint_names[int(np.argmax(gap))]
            if divergence <= self.divergence_limit:
                self._diverged_since = None
            elif self._diverged_since is None:
                self._diverged_since = now
            elif now - self._diverged_since > m.rig.mirror.divergence_window_s:
                self._hold(
                    f"diverged: measured joints {divergence:.3f} rad from the twin's for "
                    f"{now - self._diverged_since:.2f} s (limit {self.divergence_limit} rad)"
                )


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
    ):
        rig.check_embodiment(embodiment)
        self.rig = rig
        self.joints = joints
        self.dry_run = bool(dry_run)
        self._period = 1.0 / control_hz
        guard_config = guard or GuardConfig()
        # The mirror's own guard checks the targets it makes itself (catching up).
        self.guard = CollisionGuard(model, embodiment, joints, guard_config, dt=self._period)
        self._qpos = np.zeros(model.nq)
        self._qpos[joints.qpos_adr] = joints.home
        self.links: list[_Link] = []
        for entry in rig.devices:
            device = build_device(entry, embodiment, joints)
            index = np.array([joints.names.index(n) for n in joint_names_of(entry, embodiment)])
            self.links.append(_Link(self, device, index, entry.part))
        effector_of = dict.fromkeys(embodiment.body_joints, BODY)  # the body: never refused
        for e in embodiment.effectors:
            for n in e.joints:
                effector_of[n] = e.name
        self._link_effector = [effector_of[joints.names[link.index[0]]] for link in self.links]
        vmax = self.guard.max_velocity.copy()
        for link in self.links:  # no faster than a device's own cap
            if link.device.max_velocity:
                vmax[link.index] = np.minimum(vmax[link.index], link.device.max_velocity)
        self._step_cap = vmax * self._period
        hand = self.guard.hand_joints
        self._catch_up_cap = (
            np.where(hand, rig.mirror.hand_catch_up_speed, rig.mirror.arm_catch_up_speed)
            * self._period
        )
        self._cond = threading.Condition()
        self._stopping = threading.Event()
        self._seq = 0
        self._dispatched: np.ndarray | None = None
        self._t_dispatch = 0.0
        self._t_submit = time.monotonic()
        self._twin_positions = joints.home.astype(np.float64).copy()
        self._halted = ""  # why every device holds ("" = none)
        self._estop = False
        self.started = False

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> np.ndarray:
        """Connect every device; returns the measured joints in action order (the twin starts
        there). Raises :class:`MirrorError` naming the device and what to check; devices
        already connected are released."""
        for link in self.links:
            try:
                link.device.connect()
                link.stats.connected = True
            except (DeviceError, OSError, ValueError) as exc:
                self.close()
                raise MirrorError(f"cannot start mirroring: {link.name}: {exc}") from None
        return self.measured()

    def measured(self) -> np.ndarray:
        """Measured joints of every device, in action order (home where no device)."""
        q = self.joints.home.astype(np.float64).copy()
        for link in self.links:
            link.measured = link.device.read_positions()
            q[link.index] = link.measured
        return q

    def latest_measured(self) -> np.ndarray:
        """The devices' joints as their writer threads last read them (action order; the
        last dispatched target where a device has not been read yet)."""
        q = (self._dispatched if self._dispatched is not None else self.joints.home).copy()
        for link in self.links:
            if link.measured is not None:
                q[link.index] = link.measured
        return q

    def start(self, q_start: np.ndarray) -> None:
        """Start following from ``q_start`` (the measured pose the twin was reset to)."""
        self._dispatched = np.asarray(q_start, dtype=np.float64).copy()
        self._twin_positions = self._dispatched.copy()
        self._t_submit = time.monotonic()
        self.guard.reset()
        for link in self.links:
            link._last = self._dispatched[link.index].copy()
            link.start()
        self.started = True

    def close(self) -> None:
        """Hold and release every device (idempotent)."""
        self._stopping.set()
        with self._cond:
            self._cond.notify_all()
        for link in self.links:
            link.join(2.0)
            if link.stats.connected and not self.dry_run:
                try:
                    link.device.hold()
                except DeviceError as exc:
                    link.stats.errors += 1
                    link.stats.last_error = str(exc)
            link.device.disconnect()
            link.stats.connected = False

    # ------------------------------------------------------------------ per tick
    def submit(
        self, action: np.ndarray, twin_positions: np.ndarray, refused: Sequence[str] = ()
    ) -> None:
        """The twin applied ``action`` this tick (past its guard); its joints are
        ``twin_positions``; ``refused``: effectors whose command the guard refused."""
        if self._dispatched is None:
            raise RuntimeError("HardwareMirror.submit before start()")
        action = np.asarray(action, dtype=np.float64)
        previous = self._dispatched.copy()
        for link in self.links:  # a holding device is where it was held, not where we sent
            if (self._halted or link.stats.holding) and link._last is not None:
                previous[link.index] = link._last
        step = action - previous
        target = action
        if (np.abs(step) > self._step_cap * (1 + 1e-9)).any():
            # Further than one tick of motion: catch up slowly, guarded.
            target = previous + np.clip(step, -self._catch_up_cap, self._catch_up_cap)
            verdict = self.guard.check(target, self._qpos, previous)
            if not verdict.ok:
                for name in verdict.blocked:
                    sl = self.joints.slices[name]
                    target[sl] = previous[sl]
                log.warning("mirror catch-up refused: %s", verdict.reason())
            for link in self.links:
                if (target[link.index] != action[link.index]).any():
                    link.stats.catch_up_steps += 1
        for link, effector in zip(self.links, self._link_effector, strict=True):
            if effector in refused:
                link.stats.commands_refused += 1
        with self._cond:
            self._dispatched = target
            self._twin_positions = np.asarray(twin_positions, dtype=np.float64).copy()
            self._t_dispatch = time.perf_counter()
            self._t_submit = time.monotonic()
            self._seq += 1
            self._cond.notify_all()

    # ------------------------------------------------------------------ safety
    def estop(self, reason: str = "emergency stop") -> None:
        """Hold every device now; latched until :meth:`release`."""
        with self._cond:
            self._estop = True
            self._halted = f"e-stop: {reason}"
            self._cond.notify_all()
        log.error("EMERGENCY STOP (%s): every device holds until released", reason)

    def release(self) -> None:
        """Release the e-stop and any divergence hold; devices catch up with the twin slowly."""
        with self._cond:
            if any(link.stats.holding.startswith("failed") for link in self.links):
                log.error("a device failed: restart the session to mirror again")
                return
            self._estop = False
            self._halted = ""
            for link in self.links:
                if link.stats.holding.startswith("diverged"):
                    link.stats.holding = ""
                    link._diverged_since = None
            self._cond.notify_all()

    @property
    def estopped(self) -> bool:
        return self._estop

    def _device_failed(self, link: _Link, exc: Exception) -> None:
        link.stats.holding = f"failed: {exc}"
        log.error("%s failed (%s): every other device holds", link.name, exc)
        with self._cond:
            self._halted = f"{link.name} failed"
            self._cond.notify_all()

    # ------------------------------------------------------------------ report
    def summary(self) -> dict:
        out = {}
        for link in self.links:
            s = link.stats.summary()
            times = np.asarray(link.stats.write_times)
            if times.size > 1:
                span = times[-1] - times[0]
                s["write_rate_hz"] = round((times.size - 1) / span, 2) if span > 0 else None
            out[link.name] = s
        return out
