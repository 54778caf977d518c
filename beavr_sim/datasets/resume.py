"""What a run that writes a dataset does with its ``--out``: a new dataset, resume the one there
(episodes appended, the seeds already recorded skipped) or overwrite it.

:func:`plan_output` reads the folder (never writes) and :meth:`OutputPlan.describe` is the line
to print on stderr before the first episode, so a re-run never silently appends the same seeds
again. ``python -m beavr_sim.datasets generate`` uses it; ``teleop --record`` may.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from beavr_sim.datasets.shards import read_log
from beavr_sim.datasets.writer import dataset_exists
from beavr_sim.robots.identity import embodiment_label

#: The values of :attr:`OutputPlan.mode` (and of a run summary's ``mode``).
MODES = ("new", "resume", "overwrite")


@dataclass(frozen=True)
class OutputPlan:
    """What a run does with ``out``: :data:`MODES`, and the seeds already recorded there."""

    mode: str
    episodes_there: int
    seeds_there: frozenset[int]
    overwrite: bool = False  # asked for: also drops the shards of an unfinished parallel run

    def describe(self, out: Path, task: str, embodiment: str) -> str:
        if self.mode == "overwrite":
            return f"overwriting {out} ({self.episodes_there} episodes there are deleted)"
        if self.mode == "new":
            return f"new dataset at {out}"
        seeds = sorted(self.seeds_there)
        shown = ", ".join(map(str, seeds[:8])) + (", ..." if len(seeds) > 8 else "")
        return (
            f"resuming {out}: it holds {self.episodes_there} episodes; seeds of {task} on "
            f"{embodiment} already there are skipped ({shown or 'none'}); "
            "pass --overwrite to start anew"
        )


def plan_output(out: Path, task: str, embodiment: str, overwrite: bool) -> OutputPlan:
    """Resume, overwrite or create the dataset at ``out`` (reads, never writes)."""
    if not dataset_exists(out):
        mode = "overwrite" if overwrite and out.exists() and any(out.iterdir()) else "new"
        return OutputPlan(mode, 0, frozenset(), overwrite)
    total = int(json.loads((out / "meta" / "info.json").read_text())["total_episodes"])
    if overwrite:
        return OutputPlan("overwrite", total, frozenset(), overwrite)
    seeds = frozenset(
        int(r["seed"])
        for r in read_log(out)
        if r.get("kept")
        and isinstance(r.get("seed"), int)
        and r.get("task") == task
        and r.get("embodiment") in (embodiment, embodiment_label(embodiment))
    )
    return OutputPlan("resume", total, seeds)
