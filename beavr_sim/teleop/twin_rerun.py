"""``--rerun`` under ``--multiprocess``: the Rerun logger as a hook of the twin process.

The logger (:class:`~beavr_sim.viz.rerun_log.RerunLogger`) is a tick listener of the
single-process loop; here it follows the twin stage's ``after_step`` hook instead, each step
handed to it as the tick one process would give it: the step's time, the hand frames the
operator observed for it (sent on the command stream, as for the recorder), the commands
applied and the twin's state. What only the operator process knows is not logged here: the
operator's IK targets (``world/targets/...``) stay empty.

Contract: :func:`attach_rerun` returns the logger's closer; the hook never raises (the twin
stage counts a hook's errors), and the log is flushed when the process ends.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

from beavr_sim.wire.records import Tick, TwinState


@dataclass(frozen=True)
class TwinRerun:
    """The twin process's Rerun log: the ``.rrd`` path, the camera images and twin poses per
    second of session time (0: none), the session's source (logged as static)."""

    path: str
    image_hz: float = 5.0
    twin_hz: float = 30.0
    source: str | None = None


class _NoTargets:
    """The operator's IK targets, which live in the operator process: none here."""

    def targets(self) -> dict:
        return {}


class _LoopView:
    """What the logger reads from a loop, from the twin process's parts."""

    def __init__(self, process, real_time: bool):
        self.twin = process.stage.twin
        self.latencies_ms = process.stage.latencies_ms
        self.real_time = real_time
        self.dt = 1.0 / process.env.control_hz
        self.operator = _NoTargets()


def attach_rerun(process, config: TwinRerun, real_time: bool) -> Callable[[], None]:
    """Log the twin process's steps (``process``: a
    :class:`~beavr_sim.teleop.twin_process.TwinProcess`) to ``config.path``; returns the closer."""
    from beavr_sim.viz.rerun_log import RerunLogger  # local: heavy (rerun, ~360 ms)

    view = _LoopView(process, real_time)
    logger = RerunLogger(
        config.path, view, image_hz=config.image_hz, twin_hz=config.twin_hz, source=config.source
    )

    def rerun(state: TwinState) -> None:
        # one process's tick time: the virtual clock's before the step, or the wall clock
        t = time.monotonic() if real_time else state.t - view.dt
        commands = dict(process.tick_commands)
        logger(Tick(t=t, frames=tuple(process.frames), commands=commands, state=state))

    process.stage.after_step.append(rerun)
    print(f"rerun log: {config.path} (open: rerun {config.path})", file=sys.stderr)
    return logger.close
