"""The mirror's speed caps, in one place: how fast each joint may be sent, over what time a
submit's motion is spread, and how a streamed target is split into steps.

- :class:`MirrorSpeeds` builds every cap the mirror uses from the guard's velocity caps, no
  faster than a device's own (:attr:`~beavr_sim.hardware.device.Device.max_velocity`), each a
  :class:`~beavr_sim.twin.rate_limit.JointRateLimit`: ``reach`` (each joint on its own: a step
  beyond one period's reach is caught up), ``rate`` (a device's joints move together; joints no
  device drives are not limited) and ``catch_up`` (the slower catch-up speeds);
- :func:`submit_interval`: the time a submit's motion is spread over, at least
  :data:`MIN_INTERVAL_S`;
- :func:`stream_steps`: a streamed target interpolated from the last one sent, one step per
  stream interval, no step faster than :data:`STREAM_SPEED_SHARE` of the device's own cap.

Contract: pure arithmetic, no state; the counters (``rate_limited``, ``catch_up_steps``) are
kept by the mirror and reported once in its summary.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from beavr_sim.hardware.rig import MirrorConfig
from beavr_sim.twin.rate_limit import JointRateLimit

#: The shortest time (s) a submit's motion is spread over. Two commands can arrive a fraction
#: of a millisecond apart (scheduling jitter); with their true spacing the second could barely
#: move (at a spacing of 0 not at all: the target would freeze until the next heartbeat). One
#: millisecond of motion at the speed cap is a few mrad, and a streamed device is bounded
#: further by its writer (:func:`stream_steps`).
MIN_INTERVAL_S = 1e-3
#: The share of a device's own speed cap one streamed step may use.
STREAM_SPEED_SHARE = 0.9


@dataclass(frozen=True)
class MirrorSpeeds:
    """Every speed cap of the mirror (action order)."""

    #: Per action index, the speed (rad/s) the rig follows (the guard's cap, no faster than a
    #: device's own): the twin steps no faster (``TwinInterface.follow_speed_caps``).
    caps: np.ndarray
    #: The caps, each joint on its own: a step beyond one period's reach is caught up.
    reach: JointRateLimit
    #: The rate limit: a device's joints move together (its step shortened along its
    #: direction); joints no device drives are not limited.
    rate: JointRateLimit
    #: The catch-up speeds (hand or arm, per joint).
    catch_up: JointRateLimit

    @classmethod
    def of(
        cls,
        guard_caps: np.ndarray,
        devices: Sequence[tuple[np.ndarray, float | None]],
        hand_joints: np.ndarray,
        config: MirrorConfig,
    ) -> MirrorSpeeds:
        """From the guard's caps, each device's (action indices, own cap or None) and which
        joints are a hand's."""
        vmax = np.array(guard_caps, dtype=np.float64)
        for index, own in devices:  # no faster than a device's own cap
            if own:
                vmax[index] = np.minimum(vmax[index], own)
        driven = np.zeros(vmax.size, dtype=bool)
        for index, _ in devices:
            driven[index] = True
        return cls(
            caps=vmax.copy(),
            reach=JointRateLimit.of(vmax),
            rate=JointRateLimit.of(
                np.where(driven, vmax, math.inf), groups=[index for index, _ in devices]
            ),
            catch_up=JointRateLimit.of(
                np.where(hand_joints, config.hand_catch_up_speed, config.arm_catch_up_speed)
            ),
        )


def submit_interval(dt: float) -> float:
    """The time (s) a submit ``dt`` after the previous one spreads its motion over."""
    return max(dt, MIN_INTERVAL_S)


def stream_steps(
    last: np.ndarray | None,
    q: np.ndarray,
    interval: float,
    stream_hz: float | None,
    period: float,
    max_velocity: float | None,
) -> list[np.ndarray]:
    """The targets that send ``q`` to a device that wants a stream at ``stream_hz``: from
    ``last`` (the last target sent) over ``interval`` (within one stream step and one control
    period ``period``), more steps where one would pass :data:`STREAM_SPEED_SHARE` of the
    device's own cap. ``[q]`` for a device that wants no stream or before any was sent."""
    if not stream_hz or last is None:
        return [q]
    # The command's interval in steps at the device's rate, more if a step would pass the
    # device's own speed cap.
    interval = min(max(interval, 1.0 / stream_hz), period)
    n = max(1, round(interval * stream_hz))
    if max_velocity:
        largest = float(np.max(np.abs(q - last), initial=0.0))
        n = max(n, math.ceil(largest / (STREAM_SPEED_SHARE * max_velocity / stream_hz)))
    return [last + (q - last) * (k / n) for k in range(1, n + 1)]
