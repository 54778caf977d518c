"""Stream validation: accept hand frames in source-time order, count and log every rejection."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from beavr_sim.naming import check_name
from beavr_sim.wire.hand import SIDES, HandFrame

LOGGER_NAME = "beavr_sim.teleop.detector"
OUT_OF_ORDER = "out_of_order"
DUPLICATE = "duplicate"


@dataclass
class _ReasonLog:
    total: int = 0
    since_logged: int = 0
    last_logged: float = float("-inf")


class StreamValidator:
    """Per side, accepts frames whose ``t_source`` is newer than the last accepted one.

    :meth:`check` returns None (accepted) or the rejection reason (``"out_of_order"``: older
    than the last accepted frame of that side, ``"duplicate"``: same ``t_source``).
    :meth:`reject` counts a rejection found elsewhere (e.g. a parse error's reason).
    Each reason is logged on its first occurrence, then at most once per ``log_interval_s``
    with the count since the last line; ``clock`` drives that interval only.
    """

    def __init__(
        self,
        stream: str = "hand",
        *,
        log_interval_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ):
        if not log_interval_s >= 0.0:
            raise ValueError(f"log_interval_s must be >= 0, got {log_interval_s!r}")
        self.stream = stream
        self.log_interval_s = float(log_interval_s)
        self._clock = clock
        self._logger = logger if logger is not None else logging.getLogger(LOGGER_NAME)
        self._last_t_source: dict[str, float] = {}
        self._accepted = 0
        self._reasons: dict[str, _ReasonLog] = {}

    @property
    def accepted(self) -> int:
        return self._accepted

    @property
    def rejected(self) -> int:
        return sum(r.total for r in self._reasons.values())

    @property
    def rejected_by_reason(self) -> dict[str, int]:
        """A copy: reason -> count."""
        return {reason: r.total for reason, r in self._reasons.items()}

    def last_t_source(self, side: str) -> float | None:
        """``t_source`` of the last accepted frame of ``side`` (None before the first)."""
        return self._last_t_source.get(side)

    def check(self, frame: HandFrame) -> str | None:
        """None if ``frame`` is accepted (and becomes the newest of its side), else the reason."""
        if not isinstance(frame, HandFrame):
            raise TypeError(f"check takes a HandFrame, got {type(frame).__name__}")
        last = self._last_t_source.get(frame.side)
        if last is not None and frame.t_source <= last:
            reason = DUPLICATE if frame.t_source == last else OUT_OF_ORDER
            self.reject(reason, f"{frame.side} t_source {frame.t_source!r}, last accepted {last!r}")
            return reason
        self._last_t_source[frame.side] = frame.t_source
        self._accepted += 1
        return None

    def reject(self, reason: str, detail: str = "") -> None:
        """Count one rejection; log it (rate-limited per reason)."""
        if not isinstance(reason, str) or not reason:
            raise ValueError(f"reason must be a non-empty string, got {reason!r}")
        entry = self._reasons.setdefault(reason, _ReasonLog())
        entry.total += 1
        entry.since_logged += 1
        now = self._clock()
        if entry.total == 1 or now - entry.last_logged >= self.log_interval_s:
            suffix = f": {detail}" if detail else ""
            self._logger.warning(
                "%s stream: rejected %d frame(s) (%s) since the last report, %d in total%s",
                self.stream,
                entry.since_logged,
                reason,
                entry.total,
                suffix,
            )
            entry.since_logged = 0
            entry.last_logged = now

    def reset(self, side: str | None = None) -> None:
        """Forget the last accepted time (of ``side``, or of both): e.g. after a reconnect."""
        if side is None:
            self._last_t_source.clear()
        else:
            self._last_t_source.pop(check_name("side", side, SIDES), None)
