"""``python -m beavr_sim.hardware.emulators PLAN [FAULTS]``: serve device emulators from another process.

``PLAN`` is a JSON list of ``[name, kind, start]``: ``kind`` ``"xarm7"`` (``start``: 7 joint
angles, rad), ``"leap"`` (``start``: 16 motor positions, counts) or ``"feetech"`` (an RX-1
servo group, ``start``: ``{"group": name, "counts": [one per servo, in group order]}``, see
:data:`beavr_sim.hardware.feetech.config.GROUPS`; its servos get the RX-1's angle limits,
:data:`~beavr_sim.hardware.feetech.config.RX1_ANGLE_LIMITS`: multi-turn behind a gearbox, so counts
may be negative or past 4095 there, one turn 0..4095 elsewhere). ``FAULTS``: faults to start
under, :func:`beavr_sim.hardware.faults.parse_fault_specs` text (``@T`` from the start).

Prints one JSON line, ``{name: [host, port]}`` for arms and ``{name: pty path}`` for Dynamixel
and Feetech buses, once every emulator is serving. Then it reads standard input, one command a
line, and answers each with one JSON line:

* ``fault SPEC``: inject the faults of ``SPEC`` (same text as ``FAULTS``, ``@T`` from now);
  answers ``{"ack": [each fault, as text]}`` once they are in place, or ``{"error": message}``;
* ``close`` (or the end of input): stop. It then prints one JSON line of what every emulator
received (see :class:`beavr_sim.hardware.rig.EmulatedRig`): ``[time, targets]`` per servo_j
of an arm, per goal write of a hand (``{motor id: model rad}``) and per sync write of a Feetech
group (``{servo id: model rad}``, through the RX-1 servo table), then one JSON line of what the
faults did, ``{name: {"lost": requests, "dropped": replies, "corrupted": replies}}``, and exits.
* ``close counts``: the same without what they received (an empty ``{}``): a session that
  rehearses a rig reads back only the fault counts.

Every log an emulator appends to while it runs (:data:`GROWING_LOGS`, and each motor's
:data:`MOTOR_LOGS`) is kept for its last entries only (:class:`RecentLog`): a rehearsal of
hours stays within a few tens of MB per device.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

from beavr_sim.hardware.faults import parse_fault_specs
from beavr_sim.hardware.feetech.config import (
    GROUPS,
    RX1_ANGLE_LIMITS,
    SERVOS_BY_ID,
    counts_to_angle,
)
from beavr_sim.hardware.feetech.emulator import FeetechEmulator
from beavr_sim.hardware.leap.config import counts_to_model
from beavr_sim.hardware.leap.emulator import DynamixelEmulator
from beavr_sim.hardware.xarm.emulator import XArmEmulator

#: Entries of each emulator's logs (servo_j targets, goal writes, packets) kept at least.
LOG_LIMIT = 200_000


class RecentLog(list):
    """A list that keeps its last ``limit`` to ``2 * limit`` entries: once it holds twice the
    limit, the oldest half goes (amortized constant time per append)."""

    def __init__(self, limit: int):
        super().__init__()
        self.limit = int(limit)
        #: Entries dropped so far.
        self.dropped = 0

    def append(self, item) -> None:
        super().append(item)
        if len(self) >= 2 * self.limit:
            n = len(self) - self.limit
            del self[:n]
            self.dropped += n


#: What each emulator appends to for as long as it runs: its own logs, and each motor's
#: (servo's) record of register writes. Every one is bounded in the child process.
GROWING_LOGS = (
    "servo_log",
    "goal_log",
    "packet_log",
    "request_log",
    "set_state_log",
    "unknown_registers",
    "faults",
)
MOTOR_LOGS = ("writes",)


def _bound_logs(emulator) -> None:
    """Replace the emulator's whole-run logs by :class:`RecentLog` (before any client talks
    to it: the drivers connect only after the addresses line)."""
    for attr in GROWING_LOGS:
        if isinstance(getattr(emulator, attr, None), list):
            setattr(emulator, attr, RecentLog(LOG_LIMIT))
    for motor in _motors(emulator):
        for attr in MOTOR_LOGS:
            if isinstance(getattr(motor, attr, None), list):
                setattr(motor, attr, RecentLog(LOG_LIMIT // 100))


def _motors(emulator) -> list:
    """The per-motor states of a serial-bus emulator (none for the xArm)."""
    for attr in ("motors", "servos"):
        table = getattr(emulator, attr, None)
        if isinstance(table, dict):
            return list(table.values())
    return []


EXAMPLE = (
    "example: python -m beavr_sim.hardware.emulators "
    "'[[\"arm\", \"xarm7\", [0, 0, 0, 0, 0, 0, 0]]]' 'arm:freeze@2'"
)


def parse_plan(text: str) -> list[tuple[str, str, Any]]:
    """``PLAN``: a JSON list of ``[name, kind, start]``; ValueError naming what is wrong."""
    try:
        plan = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"PLAN is not JSON ({exc}): {text[:80]!r}") from None
    if not isinstance(plan, list) or not plan:
        raise ValueError(f"PLAN must be a non-empty JSON list of [name, kind, start], got {text!r}")
    for entry in plan:
        if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[0], str)):
            raise ValueError(f"each PLAN entry is [name, kind, start], got {json.dumps(entry)}")
    return [tuple(entry) for entry in plan]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m beavr_sim.hardware.emulators",
        description=__doc__,
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("plan", metavar="PLAN", help="JSON list of [name, kind, start]")
    parser.add_argument(
        "faults", metavar="FAULTS", nargs="?", default=None, help="faults to start under"
    )
    return parser


def _first_in_line() -> None:
    """The emulated devices stand in for controllers with processors of their own: ask the
    scheduler to run this process (and the threads it starts) before the rest of a busy
    machine, so a reply is not late because the host is loaded. A raised priority needs
    privileges; without them the emulators run at the normal one."""
    try:
        os.nice(-10)
    except OSError:
        pass


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    _first_in_line()
    try:
        plan = parse_plan(args.plan)
    except ValueError as exc:
        parser.error(str(exc))  # exits 2 with the usage line
    emulators: dict = {}
    where: dict = {}
    for name, kind, start in plan:
        if kind == "xarm7":
            emulators[name] = XArmEmulator(initial_joints=tuple(start), name=name)
            where[name] = [emulators[name].host, emulators[name].port]
        elif kind == "leap":
            initial = dict(enumerate(start))
            emulators[name] = DynamixelEmulator(initial_position=initial, name=name).start()
            where[name] = emulators[name].port
        elif kind == "feetech":
            group = start.get("group") if isinstance(start, dict) else None
            if group not in GROUPS:
                print(f"feetech {name!r}: group must be one of {sorted(GROUPS)}", file=sys.stderr)
                return 2
            ids = [s.id for s in GROUPS[group]]
            counts = start.get("counts", [2048] * len(ids))
            if len(counts) != len(ids):
                print(f"feetech {name!r}: {len(ids)} counts needed for {group}", file=sys.stderr)
                return 2
            initial = dict(zip(ids, counts, strict=True))
            limits = {i: RX1_ANGLE_LIMITS[i] for i in ids}
            try:
                emulator = FeetechEmulator(
                    ids, initial_position=initial, angle_limits=limits, name=name
                )
            except ValueError as exc:
                print(f"feetech {name!r}: {exc}", file=sys.stderr)
                return 2
            emulators[name] = emulator.start()
            where[name] = emulators[name].port
        else:
            print(f"unknown emulator kind {kind!r}; valid: xarm7, leap, feetech", file=sys.stderr)
            return 2
    for emulator in emulators.values():
        _bound_logs(emulator)
    if args.faults is not None:
        try:
            _inject(emulators, args.faults)
        except ValueError as exc:
            print(f"--faults: {exc}", file=sys.stderr)
            return 2
    print(json.dumps(where), flush=True)
    keep_received = True
    for line in sys.stdin:
        command, _, rest = line.strip().partition(" ")
        if command == "close":
            keep_received = rest.strip() != "counts"
            break
        if command == "fault":
            try:
                answer: dict[str, Any] = {"ack": _inject(emulators, rest)}
            except ValueError as exc:
                answer = {"error": str(exc)}
        else:
            answer = {
                "error": f"unknown command {line.strip()!r}; valid: 'fault SPEC', 'close', 'close counts'"
            }
        print(json.dumps(answer), flush=True)
    received: dict = {}
    for name, emulator in emulators.items():
        if not keep_received:
            pass
        elif isinstance(emulator, XArmEmulator):
            received[name] = [[t, list(q)] for t, q in emulator.servo_log]
        elif isinstance(emulator, FeetechEmulator):
            received[name] = _feetech_writes(emulator)
        else:
            # One entry per write: a sync write's goals, or a single motor's.
            writes: list = []
            for t, motor, counts in emulator.goal_log:
                if not writes or motor in writes[-1][1]:
                    writes.append([t, {}])
                writes[-1][1][motor] = float(counts_to_model(counts))
            received[name] = writes
        emulator.close()
    print(json.dumps(received), flush=True)
    faults = {
        name: {
            "lost": emulator.fault_state.lost,
            "dropped": emulator.fault_state.dropped,
            "corrupted": emulator.fault_state.corrupted,
        }
        for name, emulator in emulators.items()
    }
    print(json.dumps(faults), flush=True)
    return 0


def _inject(emulators: dict, text: str) -> list[str]:
    """Inject the faults of ``text`` (ValueError naming a bad one before any is injected)."""
    specs = parse_fault_specs(text, emulators)
    for spec in specs:
        emulators[spec.device].inject(spec)
    return [str(spec) for spec in specs]


def _feetech_writes(emulator: FeetechEmulator) -> list:
    """One ``[time, {servo id: model rad}]`` per sync write (its goals share one time)."""
    writes: list = []
    for t, servo_id, counts in emulator.goal_log:
        if not writes or writes[-1][0] != t:
            writes.append([t, {}])
        s = SERVOS_BY_ID[servo_id]
        writes[-1][1][servo_id] = float(counts_to_angle(counts, s.direction, s.gear))
    return writes


if __name__ == "__main__":
    sys.exit(main())
