"""The records that cross stage boundaries in one process: operator -> twin -> runners.

:class:`JointCommand` (operator -> twin and hardware), :class:`TwinState` (twin -> runners,
recorder, views) and :class:`Tick` (runner -> tick listeners: recorder, views, logs). The
hand frames the headset stage produces are :class:`beavr_sim.wire.hand.HandFrame`; their
msgpack forms between processes are in :mod:`beavr_sim.wire.messages`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class JointCommand:
    """Joint targets of one effector (arm then hand, action order) and where they came from.

    ``t_source`` / ``t_receive``: stamps of the newest hand frame that shaped the command;
    ``hold``: the effector is holding (``reason`` says why), not tracking the hand.
    """

    effector: str
    positions: np.ndarray
    t_source: float
    t_receive: float
    hold: bool = False
    reason: str = ""


@dataclass(frozen=True)
class TwinState:
    """What the twin publishes after a tick."""

    t: float
    positions: np.ndarray
    velocities: np.ndarray
    action: np.ndarray
    success: bool
    failure: bool
    terminated: bool
    truncated: bool
    info: dict = field(default_factory=dict)
    #: The collision guard refused a command this tick (those effectors held their last
    #: safe target); ``guard_blocked_effectors`` names them.
    guard_blocked: bool = False
    guard_blocked_effectors: tuple[str, ...] = ()


@dataclass(frozen=True)
class Tick:
    """One loop iteration: the frames used, the commands made, the twin's new state."""

    t: float
    frames: tuple
    commands: dict[str, JointCommand]
    state: TwinState


TickListener = Callable[[Tick], None]
