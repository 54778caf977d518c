"""What becomes of a recorded episode at its end (``datasets/episode_end.py``): the one
decision both layouts use; the recorder is told the fault, an interrupted or discarded
episode is never saved."""

from __future__ import annotations

import pytest

from beavr_sim.datasets.episode_end import EpisodeEnd, end_recorded_episode


class FakeRecorder:
    def __init__(self):
        self.calls: list[dict] = []

    def end(self, keep: bool, **info) -> bool:
        self.calls.append({"keep": keep, **info})
        return keep


@pytest.mark.parametrize(
    ("end", "keep", "success", "ended_by", "outcome", "saved"),
    [
        (EpisodeEnd(task_success=True), True, True, "auto", "saved", True),
        (EpisodeEnd(asked=("stop",)), True, False, "stop", "saved", True),
        (EpisodeEnd(asked=("discard",), task_success=True), False, True, "discard", "discarded", False),
        (EpisodeEnd(interrupted=True, task_success=True), False, False, "interrupted",
         "interrupted, not saved", False),
        (EpisodeEnd(fault="right_hand: frozen", task_success=True), False, False,
         "hardware_fault", "discarded", False),
        (EpisodeEnd(fault="right_hand: frozen", keep_faulty=True, task_success=True), True, False,
         "hardware_fault", "kept, marked hardware_fault", False),
        (EpisodeEnd(fault="x", interrupted=True, asked=("quit",)), False, False,
         "hardware_fault", "discarded", False),
    ],
)  # fmt: skip
def test_the_end_decides_keep_success_and_the_reason(end, keep, success, ended_by, outcome, saved):
    recorder = FakeRecorder()
    written = end_recorded_episode(recorder, end, seed=3, source="trace")
    assert (end.keep, end.success, end.ended_by) == (keep, success, ended_by)
    assert end.outcome(written) == outcome
    assert end.counts_as_saved(written) == saved
    (call,) = recorder.calls
    assert call == {
        "keep": keep,
        "success": success,
        "task_success": end.task_success,
        "ended_by": ended_by,
        "seed": 3,
        "source": "trace",
    }


def test_an_unknown_request_is_refused_naming_the_valid_ones():
    with pytest.raises(ValueError, match=r"valid: .*discard"):
        EpisodeEnd(asked=("pause",))
