"""``python -m beavr_sim.robots``: robot files (``docs/robots.md``).

- ``check ROBOT.toml [--task T] [--json]``: load the file, compose its scene, run gymnasium's
  ``check_env`` and print what was derived (joint limits, reach, the IK's collision pairs,
  what touches at home, finger scales) and what is missing. Exit status 0 when the check
  passed and nothing is missing, 1 when something is, 2 when the file cannot be loaded (one
  line naming the file and key).
- ``list``: the built-in embodiments.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from beavr_sim.robots.embodiment import EMBODIMENTS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.robots", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check", help="check a robot file")
    check.add_argument("robot", help="path to a robot .toml file")
    check.add_argument("--task", default=None, help="task to run check_env on")
    check.add_argument("--json", action="store_true", help="print the report as one JSON line")
    sub.add_parser("list", help="the built-in embodiments")
    args = parser.parse_args(argv)
    if args.command == "list":
        for name, spec in EMBODIMENTS.items():
            print(f"{name}: {spec.description}")
        return 0
    from beavr_sim.teleop.robot_check import (  # local: heavy (MuJoCo, gymnasium, the operator)
        check_robot,
        format_report,
    )

    try:
        report = check_robot(args.robot, args.task)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(dataclasses.asdict(report)) if args.json else format_report(report))
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
