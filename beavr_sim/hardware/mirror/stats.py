"""A mirrored device's counters and the bounded timing of its writes.

Contract: :class:`DeviceStats` is written only under the mirror's lock and reported once, by
:meth:`DeviceStats.summary`; :class:`WriteLog` keeps a fixed-size ring (memory does not grow
with the writes) and counts every write for the rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Writes whose timing each device keeps (the ring the latency percentiles come from).
WRITE_LOG_SIZE = 16384


class WriteLog:
    """Bounded timing of a device's writes: the last :data:`WRITE_LOG_SIZE` (monotonic time,
    latency in ms) pairs for percentiles, and the count and first/last times of all of them
    for the rate. Memory does not grow with the writes: the ring is resident from
    construction (np.zeros' pages would become resident one by one as the ring fills)."""

    def __init__(self, size: int = WRITE_LOG_SIZE):
        self._times = np.full(size, np.nan)
        self._latency = np.full(size, np.nan)
        self.count = 0
        self.first = math.nan
        self.last = math.nan

    def add(self, t: float, latency_ms: float) -> None:
        i = self.count % self._times.size
        self._times[i], self._latency[i] = t, latency_ms
        if self.count == 0:
            self.first = t
        self.last = t
        self.count += 1

    def _ordered(self, a: np.ndarray) -> np.ndarray:
        n = self._times.size
        if self.count <= n:
            return a[: self.count].copy()
        i = self.count % n
        return np.concatenate([a[i:], a[:i]])

    @property
    def times(self) -> np.ndarray:
        """The kept writes' times, oldest first."""
        return self._ordered(self._times)

    @property
    def latency_ms(self) -> np.ndarray:
        return self._ordered(self._latency)

    def rate_hz(self) -> float | None:
        span = self.last - self.first
        return round((self.count - 1) / span, 2) if self.count > 1 and span > 0 else None

    def summary(self) -> dict:
        lat = self.latency_ms
        return {
            "p50": float(np.percentile(lat, 50)) if lat.size else None,
            "p99": float(np.percentile(lat, 99)) if lat.size else None,
            "n": self.count,
            "window": int(lat.size),
        }


@dataclass
class DeviceStats:
    """One device's counters (written under the mirror's lock)."""

    #: Connected at some time during the run (stays True after close).
    connected: bool = False
    #: Connected now.
    connected_now: bool = False
    commands_sent: int = 0
    #: Ticks in which the twin's guard refused this device's effector (nothing was sent).
    commands_refused: int = 0
    #: Times the device was put on hold (timeout, divergence, e-stop, another device out).
    holds: int = 0
    #: Of those, on a command timeout (the pause between episodes, a stalled twin).
    timeout_holds: int = 0
    #: The furthest the measured joints were from what the device was asked (rad).
    max_divergence_rad: float = 0.0
    max_divergence_joint: str = ""
    errors: int = 0
    last_error: str = ""
    #: Times the device stopped answering, came back (within reconnect_s, where it was held),
    #: and was re-armed by the operator after failing.
    outages: int = 0
    recovered: int = 0
    rearmed: int = 0
    #: Targets limited to the catch-up speed.
    catch_up_steps: int = 0
    #: Catch-up targets the mirror's guard refused (the device held those joints).
    catch_up_refused: int = 0
    #: Targets slowed to the speed cap over the time since the previous submit.
    rate_limited: int = 0
    #: Dispatched targets never written: a newer one came before the writer took them.
    superseded: int = 0
    #: Streamed interpolations cut short by a newer target (which went out at once).
    preempted: int = 0
    #: Dispatches not written because this device's target had not changed (another
    #: device's command) and it was written within the last control period.
    unchanged: int = 0

    def __post_init__(self) -> None:
        self.writes = WriteLog()

    @property
    def write_times(self) -> list[float]:
        """Monotonic times of the last writes (at most :data:`WRITE_LOG_SIZE`)."""
        return self.writes.times.tolist()

    @property
    def write_latency_ms(self) -> list[float]:
        return self.writes.latency_ms.tolist()

    def summary(self) -> dict:
        return {
            "connected": self.connected,
            "connected_now": self.connected_now,
            "commands_sent": self.commands_sent,
            "commands_refused": self.commands_refused,
            "holds": self.holds,
            "timeout_holds": self.timeout_holds,
            "max_divergence_rad": round(self.max_divergence_rad, 4),
            "max_divergence_joint": self.max_divergence_joint,
            "errors": self.errors,
            "last_error": self.last_error,
            "outages": self.outages,
            "recovered": self.recovered,
            "rearmed": self.rearmed,
            "catch_up_steps": self.catch_up_steps,
            "catch_up_refused": self.catch_up_refused,
            "rate_limited": self.rate_limited,
            "superseded": self.superseded,
            "preempted": self.preempted,
            "unchanged": self.unchanged,
            "write_latency_ms": self.writes.summary(),
            "write_rate_hz": self.writes.rate_hz(),
        }
