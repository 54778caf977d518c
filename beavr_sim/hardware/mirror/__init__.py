"""Hardware mirroring: the devices of a rig following the twin's guarded commands.

:class:`HardwareMirror` (:mod:`.hardware_mirror`) is the facade the runners use; its behaviour
and thread contract are in that module's docstring. The package, one concept a module:

- :mod:`.state`: a device's :class:`LinkState` and :class:`HoldReason`, the frozen
  :class:`DeviceHealth` / :class:`MirrorHealth` snapshots, a
  :class:`Reading` of the measured joints, an episode's :class:`Fixtures`;
- :mod:`.dispatch`: the frozen records the twin's thread hands the writer threads;
- :mod:`.board`: the one lock and what is shared under it, and each writer's narrow port to it;
- :mod:`.link`: one device and its writer thread (hold, stream, read back, outage, re-arm);
- :mod:`.speed`: every speed cap (rate limit, catch-up speed, minimum interval, stream split);
- :mod:`.catch_up`: the guarded catch-up and its detours;
- :mod:`.divergence`: is a device doing what it was asked;
- :mod:`.stats`: the counters and the bounded write timing, reported once in the summary;
- :mod:`.errors`: one-line failure messages and the package's logger.
"""

from beavr_sim.hardware.mirror.board import MAX_FAULTS
from beavr_sim.hardware.mirror.errors import one_line
from beavr_sim.hardware.mirror.hardware_mirror import JOIN_TIMEOUT_S, HardwareMirror
from beavr_sim.hardware.mirror.link import RECONNECT_INTERVAL_S
from beavr_sim.hardware.mirror.speed import MIN_INTERVAL_S
from beavr_sim.hardware.mirror.state import (
    DeviceHealth,
    Fixtures,
    HoldReason,
    LinkState,
    MirrorHealth,
    Reading,
)
from beavr_sim.hardware.mirror.stats import WRITE_LOG_SIZE, DeviceStats, WriteLog

__all__ = [
    "JOIN_TIMEOUT_S",
    "MAX_FAULTS",
    "MIN_INTERVAL_S",
    "RECONNECT_INTERVAL_S",
    "WRITE_LOG_SIZE",
    "DeviceHealth",
    "DeviceStats",
    "Fixtures",
    "HardwareMirror",
    "HoldReason",
    "LinkState",
    "MirrorHealth",
    "Reading",
    "WriteLog",
    "one_line",
]
