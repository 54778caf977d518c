"""The end of a recorded source is not a fault, in both layouts.

A trace that stops before the task's checker fires leaves the robot holding for the session's
tail: that hold is counted as ``source_ended`` (never ``tracking_lost``), no tracking loss is
counted and no warning is logged. The operator-level rules are in
``test_operator_robustness.py``.
"""

from __future__ import annotations

import itertools
import logging

import numpy as np
import pytest
from fixtures_shared import cut_bundled_trace, trace_session_options

from beavr_sim.teleop.session import SessionOptions, build_loop
from beavr_sim.wire.ports import PortConfig, TransportConfig

#: Trace time kept of the bundled PickupBox trace: too short for the task's success.
CUT_S = 1.0


@pytest.fixture(scope="module")
def short_trace(tmp_path_factory):
    """The bundled PickupBox trace cut after :data:`CUT_S` seconds."""
    return cut_bundled_trace(tmp_path_factory.mktemp("trace") / "short.mcap", CUT_S)


def options(trace, **kwargs) -> SessionOptions:
    return trace_session_options(trace, **kwargs)


def assert_source_ended(summary) -> None:
    assert not summary.success
    holds = summary.holds["right"]
    assert "tracking_lost" not in holds, holds
    # Held from the trace's end (plus the loss timeout) to the end of the 2 s tail.
    assert holds.get("source_ended", 0) >= 40, holds
    assert summary.operator["right"]["tracking_losses"] == 0


def test_a_trace_that_ends_holds_as_source_ended_in_one_process(short_trace, caplog):
    loop = build_loop(options(short_trace))
    seen = []
    loop.listeners.append(lambda tick: seen.append(tick.commands["right"]))
    try:
        with caplog.at_level(logging.INFO, logger="beavr_sim"):
            summary = loop.run()
    finally:
        loop.twin.env.close()
    assert_source_ended(summary)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    assert "the source ended" in caplog.text  # said, at INFO
    # The hold never moves: every source_ended command repeats the one before it.
    for before, cmd in itertools.pairwise(seen):
        if cmd.reason == "source_ended":
            np.testing.assert_array_equal(cmd.positions, before.positions)


def test_a_trace_that_ends_holds_as_source_ended_in_multiprocess(short_trace, capfd):
    from beavr_sim.teleop.processes import MultiprocessSession

    opts = options(
        short_trace, multiprocess=True, transport=TransportConfig(ports=PortConfig.free())
    )
    summary = MultiprocessSession(opts).run(opts.max_seconds, stop_on_success=True)
    assert summary.processes == {"twin": "ok", "operator": "ok"}
    assert_source_ended(summary)
    # The operator process logs warnings and above to stderr (its INFO lines are not shown):
    # neither a loss nor the end of the trace may be one.
    err = capfd.readouterr().err
    assert "hand lost" not in err and "source ended" not in err, err[-2000:]
