"""A mirrored device's state: what it is doing (:class:`LinkState`), why it does not follow
(:class:`HoldReason`), and the immutable snapshots the session reads (:class:`DeviceHealth`,
:class:`MirrorHealth`), plus where an episode's fixtures stand (:class:`Fixtures`).

Contract: a device's state is an enum plus a reason enum and a one-line detail for people;
nothing parses the detail. Every value here is frozen (safe to hand across threads).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class LinkState(enum.Enum):
    """What a device is doing."""

    #: Sent the twin's (guarded) targets.
    FOLLOWING = "following"
    #: Sent targets on the way to the twin's, at the catch-up speed (after a hold, a release,
    #: a reset, a recovery).
    CATCHING_UP = "catching_up"
    #: Stays where it is (the reason says why); resumes by itself or on :meth:`release`.
    HOLDING = "holding"
    #: Stopped answering; being reconnected (every other device holds).
    OUTAGE = "outage"
    #: Not recovered: stays out (and the rest of the rig holds) until :meth:`rearm`.
    FAILED = "failed"


class HoldReason(enum.Enum):
    """Why a device is not following (``NONE`` while it follows or catches up)."""

    NONE = "none"
    #: The emergency stop is latched.
    ESTOP = "estop"
    #: No fresh command within ``command_timeout_s`` (resumes when commands come again).
    TIMEOUT = "timeout"
    #: The measured joints stayed away from what it was sent (latched until a release).
    DIVERGED = "diverged"
    #: Another device is in outage or failed.
    OTHER_DEVICE = "other_device"
    #: A read or write raised (``OUTAGE``).
    DEVICE_ERROR = "device_error"
    #: Did not answer again within ``reconnect_s`` (``FAILED``).
    NO_ANSWER = "no_answer"
    #: Answered again, but away from where it was held (``FAILED``).
    MOVED = "moved"


#: States in which a device is sent the twin's targets.
MOVING = (LinkState.FOLLOWING, LinkState.CATCHING_UP)
#: States of a device that is out (the others hold for it).
OUT = (LinkState.OUTAGE, LinkState.FAILED)


@dataclass(frozen=True)
class DeviceHealth:
    """One device's state, for the session (cheap, immutable)."""

    name: str
    state: LinkState
    reason: HoldReason
    #: One line for people ("" while following).
    detail: str


@dataclass(frozen=True)
class MirrorHealth:
    """The rig's state at one moment (:meth:`HardwareMirror.health`)."""

    #: Every device following or catching up (a command-timeout hold counts as live while
    #: commands come again: it resumes at its writer's next wake); no e-stop, nothing held,
    #: diverged, in outage or failed.
    live: bool
    devices: tuple[DeviceHealth, ...]
    #: One line per fault since :meth:`HardwareMirror.begin_episode` (e-stop, divergence,
    #: outage, failure; not command timeouts), oldest first.
    episode_faults: tuple[str, ...]

    @property
    def failed(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.devices if d.state in OUT)


@dataclass(frozen=True)
class Reading:
    """The devices' measured joints as their writers last read them
    (:meth:`HardwareMirror.latest_reading`), and when the oldest of those readings was taken."""

    #: Every joint, in action order (the last dispatched target where no device measures it).
    q: np.ndarray
    #: ``time.monotonic()`` of the oldest device reading in :attr:`q` (``-inf``: a device not
    #: read yet).
    t_oldest: float
    #: That device's name ("" without devices).
    oldest: str

    def age_s(self, now: float) -> float:
        """How old (s) the oldest reading is at ``now``."""
        return now - self.t_oldest


@dataclass(frozen=True)
class Fixtures:
    """Where an episode's fixtures (the twin's mocap bodies) stand after its reset."""

    mocap_pos: np.ndarray
    mocap_quat: np.ndarray

    @classmethod
    def of(cls, data) -> Fixtures:
        """The fixtures of an env's ``MjData`` (copied)."""
        return cls(np.array(data.mocap_pos, dtype=np.float64), np.array(data.mocap_quat))
