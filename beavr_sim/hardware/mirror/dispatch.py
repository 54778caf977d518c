"""What the twin's thread hands the mirror's writer threads: one :class:`Dispatch` per submit
and, per wake of a writer, the :class:`Orders` it works from.

Contract: both are frozen and made under the mirror's lock; a dispatch's arrays are read-only
(shared by every writer), so a writer never sees a half-written command.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beavr_sim.hardware.mirror.state import HoldReason, LinkState


@dataclass(frozen=True)
class Dispatch:
    """One submit as the writers see it (never mutated after it is made)."""

    seq: int
    target: np.ndarray  # action order
    twin: np.ndarray  # the twin's joints
    catching_up: tuple[bool, ...]  # per link: its target short of the twin's action
    t_dispatch: float  # perf_counter
    t_submit: float  # monotonic
    interval: float  # the time this target stands for

    def __post_init__(self) -> None:
        self.target.flags.writeable = False  # shared with the writers: read-only
        self.twin.flags.writeable = False


@dataclass(frozen=True)
class Orders:
    """What one writer is to do, taken under the lock."""

    dispatch: Dispatch
    #: (reason, detail) every device holds for (e-stop, another device out), or None.
    halt: tuple[HoldReason, str] | None
    latched: str  # this device's divergence hold ("" none)
    rearm: bool  # the operator asked to re-arm this (failed) device
    stopping: bool
    state: LinkState  # this device's state when the orders were taken
    releases: int  # releases and episode starts so far (a divergence timer restarts)
