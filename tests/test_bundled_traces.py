"""Bundled VR traces: one for every task on every embodiment it runs on, names checked before
files, and a missing trace named with the command that makes it."""

from __future__ import annotations

import pytest

from beavr_sim import assets
from beavr_sim.naming import UnknownNameError
from beavr_sim.tasks.registry import TASKS, task_class
from beavr_sim.traces.bundled import TaskEmbodimentError, find_bundled_trace
from beavr_sim.traces.format import TraceReader

PAIRS = [
    (task, embodiment)
    for task in TASKS
    for embodiment in (task_class(task).embodiments or ())  # Playground: no expert, no trace
]


@pytest.mark.parametrize(("task", "embodiment"), PAIRS)
def test_every_task_has_a_trace_on_every_embodiment_it_runs_on(task, embodiment):
    meta = TraceReader(find_bundled_trace(task, embodiment)).metadata
    assert (meta.task, meta.embodiment) == (task, embodiment)


def test_names_are_checked_before_files():
    with pytest.raises(UnknownNameError, match="Did you mean 'xarm7_leap_right'"):
        find_bundled_trace("pour", "xarm7_leap_rihgt")
    with pytest.raises(UnknownNameError, match="Unknown task 'puor'"):
        find_bundled_trace("puor")
    with pytest.raises(TaskEmbodimentError, match=r"^Tape does not run on rx1 \(runs on "):
        find_bundled_trace("tape", "rx1")


def test_a_missing_trace_names_the_bundled_ones_and_the_synth_command(tmp_path, monkeypatch):
    (tmp_path / "traces" / "rx1").mkdir(parents=True)
    (tmp_path / "traces" / "pour.mcap").touch()
    monkeypatch.setattr(assets, "assets_dir", lambda: tmp_path)
    with pytest.raises(FileNotFoundError) as info:
        assets.bundled_trace("PickPlace", "rx1")
    message = str(info.value)
    assert "xarm7_leap_right: pour; rx1: none" in message
    assert (
        "python -m beavr_sim.traces synth --task pick_place --embodiment rx1 --seed 0 --tries 10"
        " --out pick_place_rx1.mcap" in message
    )
