"""``python -m beavr_sim.teleop --task pour``: VR hand tracking drives the twin.

    python -m beavr_sim.teleop --task T [--embodiment E] [--source quest|trace|webxr] [--trace F]
        [--headless] [--no-viser] [--multiprocess] [--max-seconds N] [--summary-json F]
        [--rerun F.rrd [--rerun-image-hz 5] [--rerun-twin-hz 30]] [--leap-variant full|lite]
        [--record DIR --repo-id NAME --episodes N --episode-seconds S --fps 30
         --cameras front,overhead --image-size 480x640]

Sources: ``quest`` (default) binds the BEAVR Quest app's PULL sockets (8087 right, 8110 left,
8095 resolution, 8100 pause) on ``--headset-host`` (127.0.0.1 unless you give the PC's LAN
address, e.g. 0.0.0.0, so the headset can connect); ``trace`` replays a recorded VR trace
(``--trace F``, default: the task's bundled trace in ``assets/traces``); ``webxr`` serves a page
for any WebXR headset's browser on ``--webxr-host`` / ``--webxr-port`` (http://127.0.0.1:8443;
HTTPS with a self-signed certificate on a LAN address) that sends the hands and draws the twin
(see docs/webxr.md). The browser view
(viser; http://127.0.0.1:8080, ``--viser-host`` / ``--viser-port``) is on unless
``--no-viser``; the rendered twin goes to the headset (PUB on 10505)
unless ``--headless``. With ``--record DIR`` the episodes are written as a LeRobot dataset,
each one on disk as soon as it ends; live episodes start and stop on Enter (``d`` discards,
``q`` quits), the browser's Record / Discard buttons or a left-hand pinch held one second. Prints, last, one JSON summary line.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import time
from pathlib import Path

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.cameras.errors import CameraError
from beavr_sim.datasets.cli import add_camera_poses_arg, add_recording_args
from beavr_sim.hardware.device import MirrorError
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT
from beavr_sim.robots.parts import LEAP_HAND
from beavr_sim.scaling.executors import LOG_FORMAT
from beavr_sim.teleop.console import LineSafeHandler
from beavr_sim.teleop.interrupt import StopSignal, stop_on_signals

EPILOG = """exit codes:
  0  the session ran (its summary says how each run went)
  2  bad options or input (the error line names it and the valid choices)
  3  the rig could not be started (a device did not connect: the line says which, what to check)
  4  a mirrored device failed during the session and was not recovered or re-armed
  5  the rig ended the session early: it did not reach an episode's start pose within
     --sync-timeout, or spoilt 3 recorded episodes in a row
  130 interrupted by Ctrl-C (SIGINT), 143 by SIGTERM: the session still ends in order (the
      rig, the recorder and the views closed; the episode in progress dropped) and prints its
      summary, marked "interrupted": true, "ended_by": "SIGINT" / "SIGTERM"; a second
      signal aborts at once, without a summary
Device errors are one line each; --debug adds Python tracebacks. See docs/hardware.md."""

#: Exit codes of the hardware outcomes (documented in the epilog and docs/hardware.md).
EXIT_BAD_INPUT = 2
EXIT_RIG_START = 3
EXIT_DEVICE_FAILED = 4
EXIT_NOT_SYNCED = 5

SOURCES = ("quest", "trace", "webxr")
CLOCKS = ("real", "virtual", "paced")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m beavr_sim.teleop",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--task", required=True, help="task name, e.g. pour or PickupBox")
    p.add_argument(
        "--embodiment",
        default=None,
        help=f"robot: a built-in (default {DEFAULT_EMBODIMENT}) or a robot file, path/to/robot.toml "
        "(docs/robots.md)",
    )
    p.add_argument("--source", default="quest", choices=SOURCES, help="hand tracking source")
    p.add_argument("--trace", type=Path, default=None, help="VR trace (.mcap) for --source trace")
    p.add_argument("--seed", type=int, default=None, help="episode seed (trace: its own seed)")
    p.add_argument(
        "--clock",
        choices=CLOCKS,
        default=None,
        help="real time; a virtual clock (deterministic; trace only); or paced: the virtual "
        "clock slept to the control rate (deterministic at real speed; trace only). Default: "
        "virtual for a trace without the browser view, paced for a mirrored trace, real otherwise "
        "(--multiprocess: real unless given; virtual and paced run the processes in lockstep, "
        "the same episode as one process)",
    )
    p.add_argument("--headless", action="store_true", help="no rendered view to the headset")
    p.add_argument("--no-viser", action="store_true", help="no browser view")
    p.add_argument("--viser-host", default="127.0.0.1")
    p.add_argument("--viser-port", type=int, default=8080)
    p.add_argument(
        "--show-collision",
        action="store_true",
        help="browser view: draw the robots' collision geometry too (a panel checkbox toggles it)",
    )
    p.add_argument(
        "--viser-rate-hz",
        type=float,
        default=30.0,
        help="browser view updates per second at most (default 30; never slows the loop)",
    )
    p.add_argument(
        "--headset-host",
        default="127.0.0.1",
        help="address the headset sockets bind (a LAN address or 0.0.0.0 for a real headset)",
    )
    p.add_argument(
        "--headset-allow",
        default=None,
        help="IP[,IP] the Quest app's sockets accept (others refused and counted), or 'any'; "
        "needed with --mirror-hardware on a non-loopback --headset-host",
    )
    p.add_argument(
        "--webxr-host",
        default="127.0.0.1",
        help="--source webxr: address the page is served on (a LAN address or 0.0.0.0 for a "
        "headset on the network: HTTPS with a self-signed certificate)",
    )
    p.add_argument(
        "--webxr-port", type=int, default=None, help="--source webxr: port (default 8443)"
    )
    p.add_argument(
        "--token",
        default=None,
        help="session token the WebXR page must present (default: a fresh one, required on any "
        "address but loopback; given: required everywhere)",
    )
    p.add_argument("--headset-image-hz", type=float, default=10.0, help="twin images to headset")
    p.add_argument("--headset-image-size", default="640x360", help="WxH of headset images")
    p.add_argument(
        "--multiprocess",
        action="store_true",
        help="the operator (with the headset input) and the twin as processes",
    )
    p.add_argument("--max-seconds", type=float, default=None, help="stop after this long")
    p.add_argument("--repeat", type=int, default=1, help="trace: play it N times, 0 = until Ctrl-C")
    p.add_argument(
        "--summary-json",
        type=Path,
        default=None,
        help="also write the summary here ('-': stdout only; it is always the last stdout line)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument(
        "--debug", action="store_true", help="log with Python tracebacks (default: one line each)"
    )
    p.add_argument(
        "--rerun",
        type=Path,
        default=None,
        metavar="F.rrd",
        help="log hands, targets, joints, guard events, images and latencies to a Rerun "
        "recording (open it with: rerun F.rrd)",
    )
    p.add_argument(
        "--rerun-image-hz",
        type=float,
        default=5.0,
        help="camera images in the Rerun log per second of session time (default 5; 0: none)",
    )
    p.add_argument(
        "--rerun-twin-hz",
        type=float,
        default=30.0,
        help="twin body poses (3D) in the Rerun log per second of session time (default 30; "
        "0: no 3D twin)",
    )
    hw = p.add_argument_group("hardware mirroring (docs/hardware.md)")
    hw.add_argument(
        "--mirror-hardware",
        action="store_true",
        help="send every guarded command to the rig's devices too (real clock)",
    )
    hw.add_argument(
        "--hardware-config",
        default=None,
        metavar="F.toml",
        help="rig file, or 'emulated' for protocol emulators of every device (default rig.toml)",
    )
    hw.add_argument(
        "--dry-run", action="store_true", help="mirror everything but the final device write"
    )
    hw.add_argument(
        "--sync-timeout",
        type=float,
        default=None,
        metavar="S",
        help="seconds the devices may take to reach an episode's start pose (default: the rig "
        "file's sync_timeout_s, 30); past it the session ends (exit 5)",
    )
    hw.add_argument(
        "--emulate-faults",
        default=None,
        metavar="SPEC",
        help="--hardware-config emulated: faults the emulators inject (freeze, drop, corrupt, "
        "delay, disconnect; see docs/hardware.md), to rehearse a rig's faults",
    )
    p.add_argument(
        "--leap-variant",
        choices=LEAP_HAND.variants,
        default=None,
        help="the twin's LEAP hands: full (550 mA current limit) or lite (350 mA), which sets "
        "their torque cap; default full, or with --mirror-hardware the rig's hands' variant",
    )
    rec = p.add_argument_group("recording a LeRobot dataset")
    rec.add_argument("--record", type=Path, default=None, help="dataset folder to record into")
    rec.add_argument(
        "--camera",
        action="append",
        metavar="NAME=SPEC",
        help="record a real camera as observation.images.NAME (repeatable) through LeRobot's "
        "cameras; SPEC opencv:INDEX_OR_PATH, realsense:SERIAL or zmq:HOST:PORT, optionally "
        "@WIDTHxHEIGHT, then +depth on a realsense to record its depth as NAME_depth too "
        "(e.g. realsense:123456789@640x480+depth; docs/cameras.md)",
    )
    add_camera_poses_arg(rec)
    rec.add_argument(
        "--camera-stream-hz",
        type=float,
        default=0.0,
        metavar="HZ",
        help="stream camera panels to the browser view, the WebXR page and the Quest's camera "
        "panel at HZ panels per second (default 0: off; e.g. 5), off the control thread: the "
        "real cameras and the twin's renders of them, or without real cameras the twin's "
        "cameras (--camera-poses' cameras, else front) and the twin depth --cameras "
        "NAME:depth records (NAME_depth)",
    )
    rec.add_argument(
        "--camera-view",
        choices=("auto", "real", "twin", "both", "overlay"),
        default="auto",
        help="what a streamed camera panel shows first: the real camera, the twin's render of "
        "it, both side by side, or the twin blended over the real frame (the browser view "
        "changes it, with a blend slider); auto (default): both where the twin has a camera "
        "of the real camera's name (--camera-poses puts it at the real pose), else real",
    )
    rec.add_argument(
        "--quest-cameras",
        default=None,
        metavar="NAME[,NAME...]",
        help="the streamed panels the Quest app's camera panel shows (a grid of them; default: "
        "every panel of a session with real cameras, the twin's headset images without): real "
        "cameras, NAME_depth depth panels, or without real cameras the twin's panels; an "
        "unknown name stops the session at start, listing the panels there are",
    )
    rec.add_argument("--episodes", type=int, default=1, help="episodes to record (default 1)")
    start = rec.add_mutually_exclusive_group()
    start.add_argument(
        "--auto-start",
        dest="auto_start",
        action="store_true",
        default=None,
        help="start each episode at once (default for --source trace)",
    )
    start.add_argument(
        "--manual-start",
        dest="auto_start",
        action="store_false",
        help="start each episode on Enter, the Record button or a long left pinch "
        "(default for live sources)",
    )
    rec.add_argument(
        "--keep-faulty-episodes",
        action="store_true",
        help="mirrored: keep an episode the hardware spoilt (a device held, failed or "
        "diverged), marked hardware_fault in meta/beavr_episodes.jsonl (default: discard it)",
    )
    add_recording_args(rec)
    return p


class OneLineFormatter(logging.Formatter):
    """Log records as one line each: the exception's type and message, never its traceback
    (``--debug`` logs with the standard formatter)."""

    def format(self, record: logging.LogRecord) -> str:
        exc = record.exc_info
        if not exc or exc[1] is None:
            return super().format(logging.makeLogRecord({**record.__dict__, "exc_info": None}))
        plain = logging.makeLogRecord(
            {**record.__dict__, "exc_info": None, "exc_text": None, "stack_info": None}
        )
        line = super().format(plain)
        return f"{line} ({type(exc[1]).__name__}: {exc[1]})"


def configure_logging(debug: bool) -> None:
    handler = LineSafeHandler()  # a record never glues onto the progress line
    handler.setFormatter(logging.Formatter(LOG_FORMAT) if debug else OneLineFormatter(LOG_FORMAT))
    logging.basicConfig(level=logging.INFO if debug else logging.WARNING, handlers=[handler])


def hardware_outcome(report: dict) -> tuple[int, str]:
    """The exit code of a session's hardware outcome and its one line ("" when it ran)."""
    failed = report.get("failed_devices") or []
    if failed:
        hardware = report.get("hardware", {})
        why = "; ".join(
            f"{name}: {hardware.get(name, {}).get('reason') or hardware.get(name, {}).get('last_error') or 'failed'}"
            for name in failed
        )
        return EXIT_DEVICE_FAILED, (
            f"error: {', '.join(failed)} failed and was not recovered ({why}); check its "
            "power, cable and controller, then start the session again"
        )
    if report.get("stopped_early"):
        return EXIT_NOT_SYNCED, f"error: the session ended early: {report['stopped_early']}"
    return 0, ""


def explain(report: dict) -> list[str]:
    """Lines for a person, from the summary: why each effector held (reason: ticks, most
    first), listeners that failed, ticks that started late."""
    lines = []
    for effector, by_reason in sorted(report.get("holds", {}).items()):
        reasons = sorted(by_reason.items(), key=lambda kv: (-kv[1], kv[0]))
        text = ", ".join(f"{reason} {n}" for reason, n in reasons)
        lines.append(f"{effector} held (ticks by reason): {text}")
    errors = report.get("listener_errors", {})
    if errors:
        text = ", ".join(f"{name} {n}" for name, n in sorted(errors.items()))
        lines.append(f"tick listeners failed (the session went on): {text}")
    if report.get("overruns"):
        lines.append(
            f"{report['overruns']} ticks started late; {report.get('missed_ticks', 0)} control "
            "periods skipped (never caught up in a burst)"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.debug)

    try:
        from beavr_sim.teleop.session import (
            SessionOptions,
        )  # local: heavy (twin, IK, numba; not for --help)

        options = SessionOptions.from_args(args)
    except (UnknownNameError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    stop = StopSignal()
    try:
        # Kept while the summary is written too: a signal then is absorbed, never a traceback.
        with stop_on_signals(stop):
            return _run(args, options, stop)
    except KeyboardInterrupt:  # a second Ctrl-C: no summary
        print("\ninterrupted", file=sys.stderr)
        return 128 + (stop.signum or signal.SIGINT)


def _run(args: argparse.Namespace, options, stop: StopSignal) -> int:
    """The session of ``options``, its summary printed (and written); the exit code."""

    from beavr_sim.teleop.session import run_session  # local: heavy (imported once options parse)

    start = time.perf_counter()
    try:
        summary = run_session(options, interrupted=stop)
    except (UnknownNameError, ValueError, FileNotFoundError, FileExistsError, ImportError) as exc:
        if args.debug:
            logging.exception("session failed")
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (MirrorError, CameraError) as exc:
        if args.debug:
            logging.exception("rig failed")
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_RIG_START
    interrupted = stop()  # a signal after the session ended does not mark it
    report = summary.to_dict()
    report["wall_s"] = round(time.perf_counter() - start, 3)
    if interrupted:
        report["interrupted"] = True
        report["ended_by"] = stop.name
    if not args.quiet:
        for line in explain(report):
            print(line, file=sys.stderr)
    line = json.dumps(report)
    if args.summary_json is not None and str(args.summary_json) != "-":  # '-': stdout (below)
        args.summary_json.parent.mkdir(parents=True, exist_ok=True)
        args.summary_json.write_text(line + "\n")
    print(line)
    code, why = hardware_outcome(report)
    if why:
        print(why, file=sys.stderr)
    return stop.exit_code if interrupted else code


if __name__ == "__main__":
    sys.exit(main())
