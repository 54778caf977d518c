"""VR traces (MCAP): hand tracking recorded from a headset or synthesised, for replay.

``python -m beavr_sim.traces info|record|synth``; the format is in :mod:`.format` and
``docs/formats.md``.
"""

from beavr_sim.traces.format import (
    CONTROL_TOPICS,
    HAND_TOPICS,
    TraceError,
    TraceMetadata,
    TraceReader,
    TraceWriter,
)

__all__ = [
    "CONTROL_TOPICS",
    "HAND_TOPICS",
    "TraceError",
    "TraceMetadata",
    "TraceReader",
    "TraceWriter",
]
