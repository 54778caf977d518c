"""``python -m beavr_sim.traces``: inspect, record or synthesise VR traces.

- ``info TRACE``: a human summary, then one JSON line (channels, counts, duration, rates,
  metadata).
- ``record --out TRACE [--headset-host H] [--seconds N]``: record the BEAVR Quest app's hand
  streams (Ctrl-C finishes the file cleanly); times are seconds from the first frame.
- ``recover TRACE --out OUT [--task T] [--embodiment E]``: the readable frames of a truncated
  trace written as a complete one (then one JSON line: frames kept, where the file was cut).
- ``synth ...``: a trace from a task's scripted expert (:mod:`beavr_sim.synthetic.trace`;
  ``synth --help``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

from beavr_sim.traces.format import (
    HAND_TOPICS,
    TraceError,
    TraceMetadata,
    TraceReader,
    TraceWriter,
    recover_trace,
)
from beavr_sim.wire.ports import TransportConfig


def info(path: str | Path) -> int:
    reader = TraceReader(path)
    summary = reader.summary()
    meta = reader.metadata
    declared = f"{meta.frame_rate_hz:g} Hz" if meta.frame_rate_hz else "unknown"
    what = ", ".join(
        f"{k} {v}"
        for k, v in (("task", meta.task), ("embodiment", meta.embodiment), ("seed", meta.seed))
        if v not in ("", None)
    )
    print(f"{reader.path}: {meta.source} trace{', ' + what if what else ''}")
    print(
        f"  {summary['messages']} messages over {reader.duration_s:.3f} s "
        f"(from t = {reader.start_s:.3f} s); declared frame rate {declared}"
    )
    rates = reader.measured_rate_hz()
    side_of = {topic: side for side, topic in HAND_TOPICS.items()}
    for topic, count in sorted(reader.counts.items()):
        rate = rates.get(side_of.get(topic, ""))
        print(f"  {topic:<22} {count:>7} messages" + (f", {rate:.1f} Hz" if rate else ""))
    if meta.generator:
        print(f"  generator: {json.dumps(meta.generator, sort_keys=True)}")
    print(json.dumps(summary, sort_keys=True))
    return 0


def record_trace(
    out: str | Path,
    config: TransportConfig,
    seconds: float | None = None,
    metadata: TraceMetadata | None = None,
    *,
    poll_s: float = 0.05,
    log=print,
    until: Callable[[Mapping[str, int]], bool] | None = None,
) -> dict[str, int]:
    """Record the Quest streams on ``config`` into ``out`` until ``seconds`` pass, Ctrl-C, or
    ``until(messages written so far per channel)`` is true (a test stops on what it sent).

    Returns the messages written per channel.
    """
    import zmq

    from beavr_sim.headset.quest_io import QuestReceiver  # local: heavy (zmq)

    metadata = metadata or TraceMetadata(source="record")
    context = zmq.Context()
    try:
        with (
            QuestReceiver(context, config) as receiver,
            TraceWriter(out, metadata) as writer,
        ):
            endpoints = ", ".join(f"{s} {e}" for s, e in receiver.endpoints.items())
            log(f"recording to {out}; listening on {endpoints}; Ctrl-C to stop")
            deadline = None if seconds is None else time.monotonic() + seconds
            t0: float | None = None
            controls: dict[str, object] = {}
            try:
                while deadline is None or time.monotonic() < deadline:
                    for frame in receiver.poll(poll_s):
                        t0 = frame.t_receive if t0 is None else t0
                        frame = replace(
                            frame, t_source=frame.t_source - t0, t_receive=frame.t_receive - t0
                        )
                        for name, value in (
                            ("resolution", frame.resolution),
                            ("pause", frame.paused),
                        ):
                            if controls.get(name) != value:
                                writer.write_control(name, frame.t_source, value)
                                controls[name] = value
                        writer.write_hand(frame)
                    if until is not None and until(writer.counts):
                        break
            except KeyboardInterrupt:
                log("stopped; finishing the file")
            if receiver.rejected:
                log(f"rejected payloads: {dict(receiver.rejected)}")
            counts = dict(writer.counts)
    finally:
        context.term()
    log(f"wrote {out}: {counts}")
    return counts


def recover(path: Path, out: Path, task: str | None, embodiment: str | None) -> int:
    salvage = recover_trace(path, out, task=task, embodiment=embodiment)
    cut = "not cut short" if salvage.truncated_at is None else f"cut at byte {salvage.size}"
    print(
        f"{path} ({cut}): wrote {salvage.hand_frames} hand frames ({salvage.duration_s:.2f} s) "
        f"to {out}" + (f"; {salvage.invalid} invalid messages left out" if salvage.invalid else ""),
        file=sys.stderr,
    )
    print(
        json.dumps(
            {
                "out": str(out),
                "hand_frames": salvage.hand_frames,
                "duration_s": round(salvage.duration_s, 3),
                "truncated_at": salvage.truncated_at,
                "size": salvage.size,
                "invalid": salvage.invalid,
                "metadata_recovered": salvage.metadata is not None,
            }
        )
    )
    return 0


def _synth(argv: list[str]) -> int:
    """``synth ...``: the synthetic operator lives above the pipeline it drives."""
    from beavr_sim.synthetic.trace import main as synth_main  # local: heavy (mujoco)

    return int(synth_main(argv) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["synth"]:
        return _synth(argv[1:])
    parser = argparse.ArgumentParser(
        prog="python -m beavr_sim.traces", description="Inspect, record or synthesise VR traces."
    )
    commands = parser.add_subparsers(dest="command", required=True)
    p_info = commands.add_parser("info", help="summarise a trace")
    p_info.add_argument("trace", type=Path)
    p_record = commands.add_parser("record", help="record the BEAVR Quest app's hand streams")
    p_record.add_argument("--out", type=Path, required=True, help="trace file to write (.mcap)")
    p_record.add_argument(
        "--headset-host",
        default="127.0.0.1",
        help="interface to listen on for the headset (default loopback; '0.0.0.0' = every "
        "interface, needed for a headset on the LAN)",
    )
    p_record.add_argument("--seconds", type=float, default=None, help="stop after N seconds")
    p_record.add_argument("--task", default="", help="task name stored in the metadata")
    p_record.add_argument("--embodiment", default="", help="embodiment stored in the metadata")
    p_recover = commands.add_parser(
        "recover", help="write the readable frames of a truncated trace as a complete one"
    )
    p_recover.add_argument("trace", type=Path)
    p_recover.add_argument("--out", type=Path, required=True, help="trace file to write (.mcap)")
    p_recover.add_argument("--task", default=None, help="task name for the metadata")
    p_recover.add_argument("--embodiment", default=None, help="embodiment for the metadata")
    commands.add_parser("synth", help="synthesise a trace (see 'synth --help')")
    args = parser.parse_args(argv)
    try:
        if args.command == "info":
            return info(args.trace)
        if args.command == "recover":
            return recover(args.trace, args.out, args.task, args.embodiment)
        if args.seconds is not None and not args.seconds > 0:
            parser.error(f"--seconds must be positive, got {args.seconds}")
        config = TransportConfig(headset_host=args.headset_host)
        metadata = TraceMetadata(source="record", task=args.task, embodiment=args.embodiment)
        record_trace(args.out, config, args.seconds, metadata)
        return 0
    except (TraceError, ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
