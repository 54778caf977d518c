"""How a recorded episode ended, and what becomes of it: the one decision of both layouts.

A recorded episode ends on its own (``"auto"``: success plus the tail, failure, the time
limit, the end of a trace), on a request (``"stop"``, ``"toggle"``, ``"discard"``,
``"quit"``), on a hardware fault (a device held, failed or diverged, or a real camera
stopped: :attr:`~beavr_sim.datasets.recorder.EpisodeRecorder.fault`) or on Ctrl-C /
SIGTERM. Contract:

- an interrupted episode is never saved (it did not end, it was cut);
- a discarded one is never saved;
- a hardware-fault episode is saved only when asked (``--keep-faulty-episodes``), then
  marked ``hardware_fault`` and never a success; it never counts as a saved episode;
- ``ended_by`` names the first of: ``hardware_fault``, ``interrupted``, the request, ``auto``.

:func:`end_recorded_episode` hands the decision to the recorder (which writes the dataset
and ``meta/beavr_episodes.jsonl``); the single-process session calls it, and so must any
other layout that records.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The requests that end a recorded episode.
END_REQUESTS = ("toggle", "stop", "discard", "quit")


@dataclass(frozen=True)
class EpisodeEnd:
    """The facts at an episode's end: ``fault`` (the recorder's, "" when none),
    ``interrupted`` (Ctrl-C / SIGTERM), ``asked`` (the requests taken, first first),
    ``task_success`` (the task's checker) and ``keep_faulty`` (``--keep-faulty-episodes``)."""

    fault: str = ""
    interrupted: bool = False
    asked: tuple[str, ...] = ()
    task_success: bool = False
    keep_faulty: bool = False

    def __post_init__(self) -> None:
        unknown = [a for a in self.asked if a not in END_REQUESTS]
        if unknown:
            raise ValueError(f"unknown episode request(s) {unknown}; valid: {END_REQUESTS}")

    @property
    def keep(self) -> bool:
        """Whether the episode is written to the dataset."""
        return (
            "discard" not in self.asked
            and not self.interrupted
            and (not self.fault or self.keep_faulty)
        )

    @property
    def success(self) -> bool:
        """The episode's success as recorded: the task's, unless the hardware spoilt it or
        it was cut."""
        return self.task_success and not self.fault and not self.interrupted

    @property
    def ended_by(self) -> str:
        if self.fault:
            return "hardware_fault"
        if self.interrupted:
            return "interrupted"
        return self.asked[0] if self.asked else "auto"

    def outcome(self, written: bool) -> str:
        """The episode line's last words: what became of it."""
        if self.fault:
            return "kept, marked hardware_fault" if written else "discarded"
        if self.interrupted:
            return "interrupted, not saved"
        if written:
            return "saved"
        return "discarded" if self.asked else "empty, not saved"

    def counts_as_saved(self, written: bool) -> bool:
        """Whether the episode counts towards ``--episodes`` (a faulty one never does)."""
        return written and not self.fault


def end_recorded_episode(recorder, end: EpisodeEnd, **info) -> bool:
    """End ``recorder``'s episode (:class:`~beavr_sim.datasets.recorder.EpisodeRecorder`) as
    ``end`` decides, with ``info`` (seed, source, ...) in its ``meta/beavr_episodes.jsonl``
    line; returns whether it was written."""
    return recorder.end(
        keep=end.keep,
        success=end.success,
        task_success=bool(end.task_success),
        ended_by=end.ended_by,
        **info,
    )
