"""The one interface every hardware device implements (xArm7, LEAP hand, Feetech servo groups).

A device drives the joints of one part of one effector (an arm, or a hand) in the model's
joint convention: radians, the order of :class:`~beavr_sim.robots.embodiment.JointIndex`
(arm joints 1..7, LEAP motor ids 0..15). Conversions to the device's own units and zero live
inside its driver, in one tested place.

Lifecycle: :meth:`Device.connect` (raises :class:`DeviceError` naming the device and what to
check when it cannot be reached), then any number of :meth:`read_positions` /
:meth:`send_positions` / :meth:`hold`, then :meth:`disconnect` (idempotent, never raises).

Transient faults: a request whose reply does not come (or comes garbled) is asked again a few
times (each device's config says how many), each counted in :attr:`Device.retries`; only then
:class:`DeviceError`. After one, :meth:`Device.reconnect` re-opens the connection and re-reads
the joints, or raises :class:`DeviceError` (one line) within about the device's reply timeout:
safe to call again and again while a device is out.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np


class DeviceError(RuntimeError):
    """A device could not be reached, refused a command, or reported an error."""


class MirrorError(RuntimeError):
    """Hardware mirroring cannot start (a device unreachable or misconfigured)."""


class MeasuredStateError(RuntimeError):
    """A mirrored rig's measured state is not live: a device not following (held, failed, in
    outage, e-stopped), a fault this episode, or the joints away from the commands beyond the
    rig's window. It is never observed as if it were live."""


class Device(ABC):
    """One physical device. Subclasses implement the four ``_``-free hooks below."""

    #: Unique name in a rig, e.g. ``"right_arm"``.
    name: str
    #: Model joint names this device drives, in order.
    joint_names: tuple[str, ...]
    #: Rate (Hz) at which the device wants targets streamed; a mirror interpolates the twin's
    #: commands up to it (the xArm's servo mode expects ~100 Hz). None: once per command.
    stream_hz: float | None = None
    #: The device's own joint speed cap (rad/s), if it has one below the guard's: a mirror
    #: never sends targets faster than this.
    max_velocity: float | None = None
    #: Requests asked again after their reply did not come or came garbled (drivers count).
    retries: int = 0

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @abstractmethod
    def connect(self) -> None:
        """Open the connection and bring the device into streaming position control; raises
        :class:`DeviceError` naming the device and what to check."""

    @abstractmethod
    def read_positions(self) -> np.ndarray:
        """Measured joint positions (model convention, radians), shape ``(n_joints,)``."""

    @abstractmethod
    def send_positions(self, positions: np.ndarray) -> np.ndarray:
        """Stream joint targets (model convention); returns the targets actually sent, after
        any clipping the driver applies. Raises :class:`DeviceError` on a failed write."""

    @abstractmethod
    def hold(self) -> None:
        """Stop following new targets: stay at the last sent target (or the measured pose)."""

    @abstractmethod
    def disconnect(self) -> None:
        """Release the device (idempotent; never raises)."""

    def reconnect(self) -> np.ndarray:
        """Re-open the connection after a failure and return the measured joints; raises
        :class:`DeviceError` (one line) when the device still does not answer. Safe to call
        repeatedly. This default is ``disconnect()``, ``connect()``, ``read_positions()``."""
        self.disconnect()
        self.connect()
        return self.read_positions()

    def check_positions(self, positions: np.ndarray) -> np.ndarray:
        """``positions`` as a finite float64 vector of this device's length, or ValueError."""
        q = np.asarray(positions, dtype=np.float64)
        if q.shape != (self.n_joints,):
            raise ValueError(
                f"{self.name}: expected {self.n_joints} joint targets, got shape {q.shape}"
            )
        if not np.isfinite(q).all():
            raise ValueError(f"{self.name}: non-finite joint targets {q.tolist()}")
        return q

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()
