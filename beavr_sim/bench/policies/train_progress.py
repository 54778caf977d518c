"""The progress of a ``lerobot-train`` subprocess, read from its log as it grows: the step
(``| 1600/6000 [``, its progress bar, counted from the checkpoint a resumed run started at)
and the last logged loss (``step:2K ... loss:0.227``).

:class:`TrainProgress` turns new log text into a :class:`TrainStatus`; :func:`follow` waits on
the process and reports the status on a terminal as a bar, elsewhere (a log file, ``nohup``)
as one line every :data:`LINE_EVERY_S`, so an hours-long training is never silent.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from tqdm import tqdm

#: Seconds between status lines where stderr is not a terminal.
LINE_EVERY_S = 60.0
#: Seconds between looks at the log.
POLL_S = 1.0
#: The step rate (and so the time left) is measured over about the last this many seconds:
#: a machine that got busier or freer shows in it, the start-up before the first step never.
RATE_WINDOW_S = 300.0

_BAR = re.compile(r"\| *(\d+)/\d+ \[")
_LOSS = re.compile(r"\bstep:\S+ .*?\bloss:([-+0-9.eE]+)")


@dataclass(frozen=True)
class TrainStatus:
    """Where a run stands: ``step`` of ``total``, the last logged ``loss`` (None before the
    first), ``rate`` in steps per second over about the last :data:`RATE_WINDOW_S` (None until
    two steps were seen apart in time)."""

    step: int
    total: int
    loss: float | None = None
    rate: float | None = None

    def line(self, label: str) -> str:
        """``train act on PickupBox: step 1600/6000 (27 %), 3.3 step/s, ~22 min left, loss
        0.227``."""
        parts = [f"{label}: step {self.step}/{self.total} ({100 * self.step // self.total} %)"]
        if self.rate:
            left = max(self.total - self.step, 0) / self.rate
            parts.append(f"{self.rate:.2f} step/s, ~{_duration(left)} left")
        if self.loss is not None:
            parts.append(f"loss {self.loss:.4g}")
        return ", ".join(parts)


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    if minutes < 60:
        return f"{minutes} min"
    return f"{minutes // 60} h {minutes % 60:02d} min"


class TrainProgress:
    """Status of one run of ``lerobot-train`` (a fresh one, or one resumed at ``first_step``)
    from its log text, fed as it arrives; partial lines wait for their end."""

    def __init__(
        self, total: int, first_step: int = 0, clock: Callable[[], float] = time.monotonic
    ):
        self.first_step = first_step
        self._clock = clock
        #: (time, step) whenever the step changed; the oldest one at least a window old kept.
        self._seen: deque[tuple[float, int]] = deque()
        self._pending = ""
        self.status = TrainStatus(first_step, total)

    def feed(self, text: str) -> TrainStatus:
        """The status after ``text`` (the log's next characters)."""
        text = self._pending + text
        # tqdm ends a redraw with \r, LeRobot's log lines with \n: keep an unfinished tail
        cut = max(text.rfind("\r"), text.rfind("\n")) + 1
        done, self._pending = text[:cut], text[cut:]
        step, loss = self.status.step, self.status.loss
        counts = _BAR.findall(done)
        if counts:
            step = self.first_step + int(counts[-1])
        losses = _LOSS.findall(done)
        if losses:
            loss = float(losses[-1])
        now = self._clock()
        if counts and (not self._seen or self._seen[-1][1] != step):
            self._seen.append((now, step))
        while len(self._seen) > 2 and now - self._seen[1][0] >= RATE_WINDOW_S:
            self._seen.popleft()
        rate = None
        if self._seen:
            since, from_step = self._seen[0]
            if now > since and step > from_step:
                rate = (step - from_step) / (now - since)
        self.status = TrainStatus(step, self.status.total, loss, rate)
        return self.status


def follow(
    process: subprocess.Popen,
    log: Path,
    progress: TrainProgress,
    label: str,
    stream: TextIO | None = None,
) -> int:
    """Wait for ``process`` (writing ``log`` from its current end), reporting ``progress`` on
    ``stream`` (stderr); returns its exit code."""
    stream = stream or sys.stderr
    tty = stream.isatty()
    bar = None
    if tty:
        bar = tqdm(
            total=progress.status.total,
            initial=progress.first_step,
            desc=label,
            unit="step",
            file=stream,
            dynamic_ncols=True,
            leave=False,
        )
    next_line = time.monotonic() + LINE_EVERY_S
    with log.open(errors="replace") as reader:
        reader.seek(0, 2)
        while True:
            try:
                code = process.wait(timeout=POLL_S)
            except subprocess.TimeoutExpired:
                code = None
            status = progress.feed(reader.read())
            if bar is not None:
                bar.update(status.step - bar.n)
                if status.loss is not None:
                    bar.set_postfix(loss=f"{status.loss:.4g}", refresh=False)
            elif time.monotonic() >= next_line:
                print(status.line(label), file=stream, flush=True)
                next_line = time.monotonic() + LINE_EVERY_S
            if code is not None:
                break
    if bar is not None:
        bar.close()
    return code
