"""``python -m beavr_sim.hardware.emulators PLAN``: serve device emulators from another process.

``PLAN`` is a JSON list of ``[name, kind, start]``: ``kind`` ``"xarm7"`` (``start``: 7 joint
angles, rad) or ``"leap"`` (``start``: 16 motor positions, counts). Prints one JSON line,
``{name: [host, port]}`` for arms and ``{name: pty path}`` for hands, then serves until a line
``close`` (or the end of) standard input; then prints one JSON line of what every emulator
received (see :class:`beavr_sim.hardware.rig.EmulatedRig`) and exits.
"""

from __future__ import annotations

import json
import sys

from beavr_sim.hardware.dynamixel_emulator import DynamixelEmulator
from beavr_sim.hardware.leap import counts_to_model
from beavr_sim.hardware.xarm_emulator import XArmEmulator


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    emulators: dict = {}
    where: dict = {}
    for name, kind, start in json.loads(argv[0]):
        if kind == "xarm7":
            emulators[name] = XArmEmulator(initial_joints=tuple(start))
            where[name] = [emulators[name].host, emulators[name].port]
        elif kind == "leap":
            emulators[name] = DynamixelEmulator(initial_position=dict(enumerate(start))).start()
            where[name] = emulators[name].port
        else:
            print(f"unknown emulator kind {kind!r}; valid: xarm7, leap", file=sys.stderr)
            return 2
    print(json.dumps(where), flush=True)
    for line in sys.stdin:
        if line.strip() == "close":
            break
    received: dict = {}
    for name, emulator in emulators.items():
        if isinstance(emulator, XArmEmulator):
            received[name] = [[t, list(q)] for t, q in emulator.servo_log]
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
