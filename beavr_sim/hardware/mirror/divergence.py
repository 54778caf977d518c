"""Divergence judgement: is a device doing what it was asked?

A device's measured joints are compared with every target it was sent within its lag
(:attr:`~beavr_sim.hardware.rig.MirrorConfig.device_lag_s`, and the target in effect at the
lag's start): the gap is how far the reading lies outside that range, per joint. A gap above
the limit for longer than the window is a divergence (the mirror latches a hold). A catch-up
is judged the same way, so a reset never latches a hold.

Contract: :class:`DivergenceWatch` belongs to one device's writer thread (which restarts its
timer when it sees a release or a new episode); memory is bounded (the last 256 targets
sent).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: Targets each device remembers for the judgement (more than its lag holds at any rate).
ASKED_SIZE = 256


@dataclass(frozen=True)
class Judgement:
    """One reading judged."""

    #: The largest gap (rad) between the reading and what was asked.
    divergence: float
    #: The joint it is on.
    joint: str
    #: The hold's one line where the divergence outlasted the window, else "".
    latch: str


class DivergenceWatch:
    """What one device was asked within its lag, and how long its reading has been away."""

    def __init__(self, lag_s: float, window_s: float, limit: float, joints: Sequence[str]):
        self.lag_s = lag_s
        self.window_s = window_s
        self.limit = limit
        self.joints = tuple(joints)
        #: (monotonic time, target sent) within the device's lag: what it was asked to do.
        self.asked: deque[tuple[float, np.ndarray]] = deque(maxlen=ASKED_SIZE)
        #: When the reading went beyond the limit (None: within it).
        self.since: float | None = None

    def sent(self, now: float, q: np.ndarray) -> None:
        """The device was sent ``q`` at ``now``."""
        self.asked.append((now, q))

    def restart(self, now: float, q: np.ndarray) -> None:
        """The device stands at ``q`` (just read): judged from here on."""
        self.asked.clear()
        self.asked.append((now, q))
        self.since = None

    def asked_range(self, now: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Per joint, the lowest and highest target sent within the device's lag before
        ``now`` (and the one in effect at its start); None before any was sent."""
        asked = self.asked
        while len(asked) > 1 and asked[1][0] <= now - self.lag_s:
            asked.popleft()
        if not asked:
            return None
        qs = np.array([q for _, q in asked])
        return qs.min(axis=0), qs.max(axis=0)

    def judge(self, measured: np.ndarray, now: float) -> Judgement | None:
        """The reading ``measured`` at ``now`` against what was asked (None before any
        target was sent)."""
        asked = self.asked_range(now)
        if asked is None:
            return None
        lo, hi = asked
        gap = np.maximum(np.maximum(lo - measured, measured - hi), 0.0)
        divergence = float(np.max(gap))
        joint = self.joints[int(np.argmax(gap))]
        latch = ""
        if divergence <= self.limit:
            self.since = None
        elif self.since is None:
            self.since = now
        elif now - self.since > self.window_s:
            latch = (
                f"diverged: {joint} measured {divergence:.3f} rad from what it was sent for "
                f"{now - self.since:.2f} s (limit {self.limit} rad)"
            )
        return Judgement(divergence, joint, latch)
