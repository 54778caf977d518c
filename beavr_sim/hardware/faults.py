"""Faults to rehearse a rig with: what an emulated device does wrong, and when.

A :class:`FaultSpec` is one fault of one emulated device; :func:`parse_fault_specs` reads a
comma-separated list of them from a command line (``--emulate-faults``)::

    right_arm:freeze=2.5@10,right_hand:drop=0.05,body:delay_ms=20,right_arm:disconnect@30

Each part is ``DEVICE:KIND[=VALUE][@T]``. Kinds (:data:`FAULT_KINDS`):

* ``freeze=S``: the device answers nothing for ``S`` seconds; what is sent to it meanwhile is
  lost (``freeze=0`` ends a freeze early);
* ``drop=P``: from then on a fraction ``P`` (0..1) of its replies is lost (``drop=0`` ends it);
* ``corrupt=P``: a fraction ``P`` of its replies arrive garbled (a serial bus: a bad checksum;
  an xArm: a reply the SDK rejects by its header);
* ``delay_ms=D``: every reply comes ``D`` ms late (``delay_ms=0`` ends it);
* ``disconnect``: it stops answering for good (an xArm drops its TCP connection and refuses new
  ones; a serial bus stays silent, as servos without power behind a live adapter).

``@T``: the fault starts ``T`` seconds after it is given (the emulators' start for a plan, the
call for :meth:`~beavr_sim.hardware.rig.EmulatedRig.inject`); without it, at the next request
the device receives, so a test that injects a fault and then reads meets it for certain.

:class:`FaultState` is the emulator side: the faults one emulator is under, asked per request
and per reply (thread-safe; its random draws are seeded by the device name, so a run repeats).
"""

from __future__ import annotations

import math
import random
import threading
import time
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from enum import Enum

#: Fault kinds and what their value means.
FAULT_KINDS: dict[str, str] = {
    "freeze": "seconds without any reply (0 ends a freeze)",
    "drop": "fraction 0..1 of replies lost",
    "corrupt": "fraction 0..1 of replies garbled",
    "delay_ms": "milliseconds added to every reply",
    "disconnect": "no value: stops answering for good",
}
_SYNTAX = "DEVICE:KIND[=VALUE][@T], e.g. right_arm:freeze=2.5@10 or right_hand:drop=0.05"


@dataclass(frozen=True)
class FaultSpec:
    """One fault of one emulated device (see the module docstring)."""

    device: str
    kind: str
    #: freeze: seconds; drop / corrupt: a fraction 0..1; delay_ms: ms; disconnect: unused (0).
    value: float = 0.0
    #: Seconds after the fault is given; None: at the device's next request.
    at_s: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.device, str) or not self.device:
            raise ValueError(f"fault device must be a device name, got {self.device!r}")
        if self.kind not in FAULT_KINDS:
            raise ValueError(
                f"fault kind {self.kind!r} of {self.device}: valid kinds {list(FAULT_KINDS)}"
            )
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ValueError(f"{self}: the value must be a finite number, got {v!r}")
        if self.kind in ("drop", "corrupt") and not 0.0 <= v <= 1.0:
            raise ValueError(f"{self}: {self.kind} takes a fraction in 0..1, got {v!r}")
        if self.kind in ("freeze", "delay_ms") and v < 0:
            raise ValueError(f"{self}: {self.kind} takes a number >= 0, got {v!r}")
        if self.kind == "disconnect" and v != 0:
            raise ValueError(f"{self}: disconnect takes no value")
        t = self.at_s
        if t is not None and (
            isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t) or t < 0
        ):
            raise ValueError(f"fault {self.device}:{self.kind}: @T must be >= 0 s, got {t!r}")

    def __str__(self) -> str:
        value = "" if self.kind == "disconnect" else f"={self.value:g}"
        at = "" if self.at_s is None else f"@{self.at_s:g}"
        return f"{self.device}:{self.kind}{value}{at}"


def parse_fault_spec(part: str, device_names: Iterable[str]) -> FaultSpec:
    """One ``DEVICE:KIND[=VALUE][@T]``; ValueError naming the bad part, the valid kinds and
    the valid device names."""
    names = list(device_names)
    text = part.strip()

    def bad(why: str) -> ValueError:
        return ValueError(
            f"fault {text!r}: {why}; syntax {_SYNTAX}; kinds {list(FAULT_KINDS)}; devices {names}"
        )

    device, sep, rest = text.partition(":")
    if not sep or not device:
        raise bad("no DEVICE: before the kind")
    if device not in names:
        raise bad(f"unknown device {device!r}")
    rest, at_sep, at_text = rest.partition("@")
    kind, eq, value_text = rest.partition("=")
    if kind not in FAULT_KINDS:
        raise bad(f"unknown kind {kind!r}")
    if kind == "disconnect" and eq:
        raise bad("disconnect takes no value")
    if kind != "disconnect" and not eq:
        raise bad(f"{kind} needs a value ({FAULT_KINDS[kind]})")
    try:
        value = float(value_text) if eq else 0.0
    except ValueError:
        raise bad(f"value {value_text!r} is not a number ({FAULT_KINDS[kind]})") from None
    try:
        at = float(at_text) if at_sep else None
    except ValueError:
        raise bad(f"@{at_text!r} is not a time in seconds") from None
    try:
        return FaultSpec(device, kind, value, at)
    except ValueError as exc:
        raise bad(str(exc)) from None


def parse_fault_specs(text: str, device_names: Iterable[str]) -> tuple[FaultSpec, ...]:
    """Comma-separated :func:`parse_fault_spec` parts (empty text: no faults)."""
    names = list(device_names)
    return tuple(parse_fault_spec(p, names) for p in text.split(",") if p.strip())


class Verdict(Enum):
    """What an emulator does with a request that just arrived."""

    SERVE = "serve"
    LOSE = "lose"  # frozen: the request is lost, nothing answers
    DISCONNECTED = "disconnected"  # for good


class Fate(Enum):
    """What becomes of one reply."""

    SEND = "send"
    DROP = "drop"
    CORRUPT = "corrupt"


class FaultState:
    """The faults one emulated device is under (thread-safe). Counters: :attr:`lost` (requests
    lost to a freeze or a disconnect), :attr:`dropped`, :attr:`corrupted` (replies)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._lock = threading.Lock()
        self._rng = random.Random(zlib.crc32(name.encode()))
        self._pending: list[tuple[float | None, FaultSpec]] = []
        self._frozen_until = -math.inf
        self._disconnected = False
        self._drop = 0.0
        self._corrupt = 0.0
        self._delay_s = 0.0
        self.lost = 0
        self.dropped = 0
        self.corrupted = 0

    def add(self, spec: FaultSpec, now: float | None = None) -> None:
        """Take ``spec`` (its ``at_s`` counts from ``now``, default the monotonic clock)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            start = None if spec.at_s is None else now + spec.at_s
            self._pending.append((start, spec))
            self._activate(now, next_request=False)

    def admit(self, now: float | None = None) -> Verdict:
        """A request arrived: serve it, lose it (frozen), or the device is gone."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._activate(now, next_request=True)
            if self._disconnected:
                self.lost += 1
                return Verdict.DISCONNECTED
            if now < self._frozen_until:
                self.lost += 1
                return Verdict.LOSE
            return Verdict.SERVE

    def fate(self) -> Fate:
        """What becomes of the reply about to be sent."""
        with self._lock:
            self._activate(time.monotonic(), next_request=False)
            if self._drop and self._rng.random() < self._drop:
                self.dropped += 1
                return Fate.DROP
            if self._corrupt and self._rng.random() < self._corrupt:
                self.corrupted += 1
                return Fate.CORRUPT
            return Fate.SEND

    @property
    def delay_s(self) -> float:
        """How late every reply comes now (s)."""
        with self._lock:
            self._activate(time.monotonic(), next_request=False)
            return self._delay_s

    def disconnected(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._activate(now, next_request=False)
            return self._disconnected

    def _activate(self, now: float, *, next_request: bool) -> None:
        keep: list[tuple[float | None, FaultSpec]] = []
        for start, spec in self._pending:
            if (start is None and not next_request) or (start is not None and start > now):
                keep.append((start, spec))
                continue
            begin = now if start is None else start
            if spec.kind == "freeze":
                self._frozen_until = begin + spec.value if spec.value > 0 else -math.inf
            elif spec.kind == "drop":
                self._drop = spec.value
            elif spec.kind == "corrupt":
                self._corrupt = spec.value
            elif spec.kind == "delay_ms":
                self._delay_s = spec.value / 1000.0
            else:
                self._disconnected = True
        self._pending = keep
