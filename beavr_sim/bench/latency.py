"""``python -m beavr_sim.bench latency``: the ``--multiprocess`` pipeline's end-to-end latency,
measured as the BEAVR paper's Table V (issue 20).

A load generator process speaks the BEAVR Quest app's wire protocol: it PUSHes keypoint
strings (``format_keypoints`` of a bundled human-hand trace, played forwards and backwards at
real speed) to the detector's Quest PULL ports at the headset rate, one per hand the
embodiment uses, and the pause status ``High`` with each app frame. The pipeline under test
is the ``--multiprocess`` runner (``--layout processes``: the operator process, which owns
the headset's sockets and the detector's parsing, and the twin process, over loopback
ZeroMQ) or the single-process runner (``--layout single``), mirroring to the emulated hardware
(``hardware_config="emulated"``), with a timing log written by the twin: the benchmark
attaches to the twin stage's hooks (:func:`attach_twin_timing`, a
:class:`~beavr_sim.teleop.process_config.Attachment` of the twin process; the single process's
command hook), as any user's code can.

The pipeline is event-driven: one command per hand frame at the headset rate, each applied by
the twin on arrival and submitted to the hardware mirror at once; the twin also submits a
heartbeat once per physics period when no command came, carrying the ``t_source`` values
already in effect. So every figure below is over **distinct commands**: a log entry (applied
command, or driver write) whose ``t_source`` equals the previous entry's for that effector is
a *repeat* (a heartbeat, or a command re-applied without a new frame behind it): counted in
``repeats``, left out of the rate, the jitter and the latency.

What each number spans (all clocks are ``time.monotonic`` on one machine):

- ``latency_twin_ms``: generator send (just before ``socket.send`` of the keypoint string) ->
  the command derived from it handed to the twin's actuators (``TwinInterface.command``). The
  frame behind a command is found from the command's ``t_source``, the detector's receive
  stamp of the frame the command was made for: its send is the generator's latest send on
  that hand's stream at or before that stamp.
- ``latency_driver_ms``: generator send -> the emulated device's driver call that wrote the
  first target derived from it having returned (hardware mirror writer thread). The write's
  time is its hand-off to the mirror plus the mirror's measured hand-off -> write time.
- ``send_to_detector_ms``: generator send -> the detector's receive stamp (the transport and
  the wake-up); ``detector_to_twin_ms``: the rest (what the twin's own ``latency_ms``
  reports), in ``stages_ms`` split at the operator's command start and the twin's receipt.
- ``command_hz``: distinct commands applied to the twin per second for the effector against
  ``target_hz`` = the headset rate (one command per frame); ``write_hz``: distinct driver
  writes per second per device, against the same target (devices no hand effector drives,
  e.g. RX-1's ``body``: every write, against the twin's ``control_hz``). ``jitter_ms``:
  standard deviation of the interval between successive distinct commands (writes).
- ``frames`` (per effector, for its hand's stream): ``sent`` by the generator, ``received``
  by the detector, ``dropped`` = sent - received, ``superseded_detector`` (replaced by a newer
  payload within one detector poll), ``superseded_operator`` (observed by the operator but
  not turned into their own command because a newer one was already queued; 0 until the
  operator reports it), ``superseded`` (the two together) and ``rejected`` (by the detector's
  validator; it counts all streams together, so this is per side only for one-handed
  embodiments, else None: see the session's ``frames.rejected``).
- ``errors`` / ``holding`` (per device): the hardware mirror's own account; once a device
  fails every device of that rig holds (no more writes), so its write rate falls.
- ``floor``: a bare ZeroMQ PUSH -> PULL hop on loopback with a keypoint string of the same
  size at the same rate (sender in its own process, blocking receiver), run just before the
  pipeline in the same invocation; ``over_floor`` is latency / floor at p50 and p99.

``--sweep`` runs 1, 2, 4 and 8 hand effectors at 90 Hz: one ``xarm7_leap_right`` session for
1, else ``n / 2`` ``xarm7_leap_bimanual`` sessions running concurrently, each with its own
ports and emulated rig, one headset each played by the one load generator process (on one
frame clock: every session's frames are due at the same instants). All of them share this
machine's cores (and the generator, the emulators and the harness too), so the growth
measures contention on one machine as much as the pipeline. Per effector count it reports
send -> twin and send -> driver pooled over all effectors (devices) of all sessions, and the
p99 growth from 1 to 4 effectors against :data:`SWEEP_P99_GROWTH_TARGET`.

The first ``WARMUP_S`` of the stream (processes settling, the operator anchoring) is left out.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.assets import bundled_trace
from beavr_sim.bench.machine import cold_factor
from beavr_sim.headset.quest_protocol import format_keypoints
from beavr_sim.traces.format import TraceReader
from beavr_sim.wire.ports import PortConfig, TransportConfig, free_tcp_ports

#: config -> (embodiment, headset stream rate Hz, task) as in the paper's Table V (4: RX-1).
CONFIGS = {
    1: ("xarm7_leap_right", 30.0, "PickPlace"),
    2: ("xarm7_leap_right", 90.0, "PickPlace"),
    3: ("xarm7_leap_bimanual", 30.0, "PickPlace"),
    4: ("rx1", 90.0, "PickPlace"),
}
#: BEAVR's published one-way latency figures (paper, Table V), for the report.
BEAVR_TABLE_V = {
    "latency_ms_at_90hz": 10.1,
    "latency_ms_at_30hz": 33.0,
    "jitter_ms": [0.13, 0.90],
    "pct_of_target_rate": [99.2, 99.4],
}
WARMUP_S = 0.5
#: ``--sweep``: effector counts, headset rate, task, and the p99 growth allowed from 1 to 4.
SWEEP_COUNTS = (1, 2, 4, 8)
SWEEP_HZ = 90.0
SWEEP_TASK = "PickPlace"
SWEEP_P99_GROWTH_TARGET = 1.5


def _stats(values) -> dict:
    a = np.asarray(values, dtype=float)
    if not a.size:
        return {"p50": None, "p95": None, "p99": None, "max": None, "mean": None, "n": 0}
    return {
        "p50": round(float(np.percentile(a, 50)), 4),
        "p95": round(float(np.percentile(a, 95)), 4),
        "p99": round(float(np.percentile(a, 99)), 4),
        "max": round(float(a.max()), 4),
        "mean": round(float(a.mean()), 4),
        "n": int(a.size),
    }


def _hand_payloads(embodiment: str, task: str, sides: list[str]) -> tuple[dict, float]:
    """Keypoint strings per side of the bundled trace at 1 ms resolution: ({side: (times,
    payloads)}, duration). Traces of one hand feed the right hand of a one-armed embodiment;
    two-handed ones come from the RX-1 recordings (a human's two hands)."""
    path = bundled_trace(task, "rx1" if len(sides) > 1 else embodiment)
    by_side: dict[str, tuple[list, list]] = {s: ([], []) for s in sides}
    for t, kind, frame in TraceReader(path).events():
        if kind == "hand" and frame.side in by_side:
            by_side[frame.side][0].append(float(t))
            by_side[frame.side][1].append(format_keypoints(frame).encode())
    missing = [s for s, (ts, _) in by_side.items() if not ts]
    if missing:
        raise ValueError(f"trace {path} has no {missing} hand frames")
    t0 = min(ts[0] for ts, _ in by_side.values())
    duration = max(ts[-1] for ts, _ in by_side.values()) - t0
    return {s: (np.asarray(ts) - t0, p) for s, (ts, p) in by_side.items()}, duration


#: The load generator spins (busy-waits) this long before each frame is due.
GENERATOR_SPIN_S = 0.0015


def generator_main(
    headsets: list[tuple[dict, dict, float]],
    rate_hz: float,
    seconds: float,
    conn,
    start_at: float | None = None,
) -> None:
    """The load generator (own process): plays one headset per session, ``headsets`` =
    [(endpoints, payloads, duration)], all on one frame clock at ``rate_hz`` for
    ``seconds``, from ``start_at`` (``time.monotonic``) or as soon as it is connected; the
    send times per session and side go back through the pipe ``conn``. One process for
    every session: one spinning process (below) instead of one per session, which on a
    small machine took the pipelines' CPU in the sweep."""
    import zmq

    context = zmq.Context()
    sessions = []
    for endpoints, payloads, duration in headsets:
        socks = {}
        for name, endpoint in endpoints.items():
            s = context.socket(zmq.PUSH)
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.SNDHWM, 1000)
            s.connect(endpoint)
            socks[name] = s
        sent: dict[str, list[float]] = {side: [] for side in payloads}
        sessions.append((socks, payloads, duration, sent))
    # the connections are up before the first frame
    start = max(start_at or 0.0, time.monotonic() + 0.3)
    time.sleep(max(0.0, start - time.monotonic()))
    period = 1.0 / rate_hz
    k = 0
    while True:
        t_due = start + k * period
        if t_due - start >= seconds:
            break
        # Sleep to just before the frame is due, then spin: a sleep alone wakes 0.1-1 ms
        # late, by a varying amount (the headset's own frame clock does not).
        delay = t_due - time.monotonic() - GENERATOR_SPIN_S
        if delay > 0:
            time.sleep(delay)
        while time.monotonic() < t_due:
            pass
        for socks, payloads, duration, sent in sessions:
            # Played forwards, then backwards, and so on: the hand never jumps back to the
            # recording's start (the operator would reject the jump and hold: a gap in the
            # rate).
            phase = ((time.monotonic() - start) % (2 * duration)) if duration > 0 else 0.0
            trace_t = phase if phase <= duration else 2 * duration - phase
            for side, (times, data) in payloads.items():
                i = min(int(np.searchsorted(times, trace_t, side="right")) - 1, len(data) - 1)
                payload = data[max(0, i)]
                t_send = time.monotonic()
                socks[side].send(payload)
                sent[side].append(t_send)
            if "pause" in socks:
                socks["pause"].send(b"High")
        k += 1
    conn.send_bytes(json.dumps([sent for *_, sent in sessions]).encode())
    for socks, *_ in sessions:
        for s in socks.values():
            s.close()
    context.term()


def floor_sender_main(endpoint: str, payload: bytes, rate_hz: float, n: int, conn) -> None:
    """The transport floor's sender (own process): ``n`` payloads at ``rate_hz``."""
    import zmq

    context = zmq.Context()
    s = context.socket(zmq.PUSH)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(endpoint)
    time.sleep(0.3)
    sent = []
    start = time.monotonic()
    for k in range(n):
        delay = start + k / rate_hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        sent.append(time.monotonic())
        s.send(payload)
    conn.send_bytes(json.dumps(sent).encode())
    s.close()
    context.term()


def transport_floor(payload: bytes, rate_hz: float, seconds: float) -> dict:
    """A bare PUSH -> PULL hop on loopback: send -> receive latency (ms) by order."""
    import zmq

    endpoint = f"tcp://127.0.0.1:{free_tcp_ports(1)[0]}"
    context = zmq.Context()
    pull = context.socket(zmq.PULL)
    pull.setsockopt(zmq.LINGER, 0)
    pull.bind(endpoint)
    n = max(10, int(seconds * rate_hz))
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(
        target=floor_sender_main, args=(endpoint, payload, rate_hz, n, child), daemon=True
    )
    proc.start()
    received = []
    try:
        while len(received) < n:
            if not pull.poll(int((seconds + 20) * 1000)):
                break
            pull.recv()
            received.append(time.monotonic())
        sent = json.loads(parent.recv_bytes()) if parent.poll(10.0) else []
    finally:
        proc.join(5.0)
        if proc.is_alive():
            proc.kill()
        pull.close()
        context.term()
    m = min(len(sent), len(received))
    lat = [(r - s) * 1e3 for s, r in zip(sent[:m], received[:m], strict=True)]
    return {
        "payload_bytes": len(payload),
        "rate_hz": rate_hz,
        "sent": len(sent),
        "received": len(received),
        "latency_ms": _stats(lat),
        "samples_ms": lat,
    }


def _latest_send(sends: np.ndarray, stamps) -> np.ndarray:
    """Index of the latest send at or before each stamp (-1: none)."""
    return np.searchsorted(sends, np.asarray(stamps, dtype=float), side="right") - 1


def _rate(times) -> tuple[float | None, dict]:
    """Rate (Hz) over ``times`` (seconds, ascending) and the statistics (ms) of the intervals
    between them."""
    t = np.asarray(times, dtype=float)
    if t.size < 2 or t[-1] <= t[0]:
        return None, {"std_ms": None, "mean_ms": None, "p99": None, "max": None}
    intervals = np.diff(t) * 1e3
    hz = (t.size - 1) / (t[-1] - t[0])
    return float(hz), {
        "std_ms": round(float(intervals.std()), 4),
        "mean_ms": round(float(intervals.mean()), 4),
        **{k: v for k, v in _stats(intervals).items() if k in ("p99", "max")},
    }


def _pct(hz: float | None, target_hz: float) -> float | None:
    return round(100 * hz / target_hz, 2) if hz else None


def analyse(
    log: dict,
    sent: dict,
    sides: dict[str, str],
    window: tuple[float, float],
    headset_hz: float,
) -> dict:
    """Per effector and per device figures from the twin's timing log and the generator's
    send times (``{side: [t_send]}``); ``sides``: effector -> the hand stream that drives it.
    Only entries inside ``window`` count; an entry repeating the previous entry's ``t_source``
    (over the whole log) is a repeat: counted, left out of rate, jitter and latency. Each
    effector and device keeps its latency samples (ms) under ``"_samples"``."""
    control_hz = float(log["control_hz"])
    lo, hi = window
    effectors = {}
    for name, side in sides.items():
        sends = np.asarray(sent.get(side, []), dtype=float)
        fresh, repeats, prev = [], 0, None
        for t_apply, t_source in log["applied"].get(name, []):
            repeat = prev is not None and t_source == prev
            prev = t_source
            if not lo <= t_apply <= hi:
                continue
            if repeat:
                repeats += 1
            else:
                fresh.append((t_apply, t_source))
        hz, jitter = _rate([t for t, _ in fresh])
        # The input's own jitter: the generator's sends in the same window (its sleep wakes
        # late by a varying amount), a floor under the commands' jitter.
        _, send_jitter = _rate(sends[(sends >= lo) & (sends <= hi)])
        stamped = [(t, ts) for t, ts in fresh if ts > 0]
        idx = _latest_send(sends, [ts for _, ts in stamped])
        twin_ms, det_ms, rest_ms = [], [], []
        for (t_apply, t_source), i in zip(stamped, idx, strict=True):
            if i >= 0:
                twin_ms.append((t_apply - sends[i]) * 1e3)
                det_ms.append((t_source - sends[i]) * 1e3)
                rest_ms.append((t_apply - t_source) * 1e3)
        # Where the time goes between the detector's stamp and the twin's actuators (the
        # twin's stage log: detector stamp, operator's command start, twin took it, applied).
        stages, prev_stamp = [], None
        for st in log.get("stages", {}).get(name, []):
            if st[0] != prev_stamp and lo <= st[3] <= hi:  # a frame's first command only
                stages.append(st)
            prev_stamp = st[0]
        effectors[name] = {
            "side": side,
            "target_hz": float(headset_hz),
            "command_hz": round(hz, 3) if hz else None,
            "pct_of_target": _pct(hz, headset_hz),
            "commands_applied": len(fresh),
            "repeats": repeats,
            "jitter_ms": jitter,
            "send_jitter_ms": send_jitter,
            "latency_twin_ms": _stats(twin_ms),
            "send_to_detector_ms": _stats(det_ms),
            "detector_to_twin_ms": _stats(rest_ms),
            "stages_ms": {
                "detector_to_operator_command": _stats([(c - d) * 1e3 for d, c, _, _ in stages]),
                "operator_command_to_twin": _stats([(k - c) * 1e3 for _, c, k, _ in stages]),
                "twin_guard_and_apply": _stats([(a - k) * 1e3 for _, _, k, a in stages]),
            },
            "_samples": twin_ms,
        }
    submits = log.get("submits", [])
    submit_t = np.asarray([t for t, _ in submits], dtype=float)
    devices = {}
    for link in log.get("links", []):
        name, effector = link["name"], link["effector"]
        driven = effector in sides  # by a hand effector (RX-1's body is not)
        sends = np.asarray(sent.get(sides.get(effector), []), dtype=float)
        fresh, repeats, prev = [], 0, None
        for t_take, w_ms in zip(link["write_times"], link["write_latency_ms"], strict=False):
            if not driven:
                if lo <= t_take <= hi:
                    fresh.append((t_take, None, None, None))
                continue
            # the tick the writer took: the latest submit at or before its take
            k = int(np.searchsorted(submit_t, t_take, side="right")) - 1
            t_sub, in_effect = submits[k] if k >= 0 else (None, {})
            t_source = float(in_effect.get(effector, 0.0))
            repeat = prev is not None and t_source == prev
            prev = t_source
            if t_source <= 0 or not lo <= t_take <= hi:
                continue  # before the effector's first command, or outside the window
            if repeat:
                repeats += 1
            else:
                fresh.append((t_take, t_sub, t_source, w_ms))
        hz, jitter = _rate([w[0] for w in fresh])
        lat = []
        if driven and fresh:
            idx = _latest_send(sends, [w[2] for w in fresh])
            for (_, t_sub, _, w_ms), i in zip(fresh, idx, strict=True):
                if i >= 0:
                    lat.append((t_sub + w_ms / 1e3 - sends[i]) * 1e3)
        target = float(headset_hz) if driven else control_hz
        devices[name] = {
            "effector": effector,
            "target_hz": target,
            "write_hz": round(hz, 3) if hz else None,
            "pct_of_target": _pct(hz, target),
            "writes": len(fresh),
            "repeats": repeats if driven else None,
            "jitter_ms": jitter,
            "latency_driver_ms": _stats(lat),
            "_samples": lat,
        }
    return {"effectors": effectors, "devices": devices}


def frame_counts(sent: dict, detector: dict, operator: dict, streams) -> dict:
    """The session's frame accounting per hand stream, from the generator's send counts
    (``{side: n}``) and the detector's and operator's results (read defensively: the
    operator reports ``frames_superseded`` only once the event-driven design lands)."""
    received = detector.get("quest_received", {}) or {}
    det_sup = detector.get("frames_superseded", {}) or {}
    op_sup = operator.get("frames_superseded", {}) or {}
    if not isinstance(op_sup, dict):
        op_sup = {}
    return {
        "sent": {s: int(sent.get(s, 0)) for s in streams},
        "received": {s: int(received.get(s, 0)) for s in streams},
        "dropped": {s: int(sent.get(s, 0)) - int(received.get(s, 0)) for s in streams},
        "passed_on": detector.get("frames_received", 0),
        "superseded": {s: int(det_sup.get(s, 0)) for s in streams},
        "superseded_operator": {s: int(op_sup.get(s, 0)) for s in streams},
        "superseded_total": {s: int(det_sup.get(s, 0)) + int(op_sup.get(s, 0)) for s in streams},
        "rejected": detector.get("frames_rejected", 0),
        "rejected_by_reason": detector.get("rejected_by_reason", {}),
    }


def effector_frames(frames: dict, side: str) -> dict:
    """One hand stream's share of :func:`frame_counts` (rejected: the detector counts all
    streams together, so a per side figure only where there is one stream, or a dict)."""
    rejected = frames["rejected"]
    if isinstance(rejected, dict):
        rejected = int(rejected.get(side, 0))
    elif len(frames["sent"]) != 1:
        rejected = None
    return {
        "sent": frames["sent"].get(side, 0),
        "received": frames["received"].get(side, 0),
        "dropped": frames["dropped"].get(side, 0),
        "superseded_detector": frames["superseded"].get(side, 0),
        "superseded_operator": frames["superseded_operator"].get(side, 0),
        "superseded": frames["superseded_total"].get(side, 0),
        "rejected": rejected,
    }


def _over_floor(lat: dict, floor_latency: dict) -> dict:
    return {
        q: round(lat[q] / floor_latency[q], 1) if lat[q] and floor_latency.get(q) else None
        for q in ("p50", "p99")
    }


_PAYLOADS: dict = {}


@dataclass
class LiveSession:
    """One pipeline under test: its stream, its session and, once run, what it left."""

    embodiment: str
    task: str
    rate_hz: float
    mirror: bool
    effectors: dict[str, str]  # effector -> hand stream
    streams: list[str]
    payloads: dict
    duration: float
    transport: object = None
    session: object = None
    log_path: str | None = None
    startup_s: float | None = None
    sent: dict = field(default_factory=dict)
    died: list = field(default_factory=list)
    log: dict | None = None
    layout: str = "processes"


def prepare(
    embodiment: str, task: str, rate_hz: float, mirror: bool, layout: str = "processes"
) -> LiveSession:
    """The stream for ``embodiment`` (payloads cached per embodiment and task)."""
    from beavr_sim.robots import make_embodiment  # local: heavy (mujoco)

    effectors = {e.name: e.side for e in make_embodiment(embodiment).effectors}
    streams = sorted(set(effectors.values()))
    key = (embodiment, task, tuple(streams))
    if key not in _PAYLOADS:
        _PAYLOADS[key] = _hand_payloads(embodiment, task, streams)
    payloads, duration = _PAYLOADS[key]
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    return LiveSession(
        embodiment, task, rate_hz, mirror, effectors, streams, payloads, duration, layout=layout
    )


def _max_payload(lives) -> bytes:
    return max((p for live in lives for _, ps in live.payloads.values() for p in ps), key=len)


def start_session(live: LiveSession) -> None:
    """Start ``live``'s ``--multiprocess`` pipeline on its own free ports, with a timing log."""
    from beavr_sim.teleop.process_config import (  # local: heavy (the pipeline: mink, scipy)
        Attachment,
    )
    from beavr_sim.teleop.processes import (  # local: heavy (the pipeline: mink, scipy)
        MultiprocessSession,
    )
    from beavr_sim.teleop.session import SessionOptions  # local: heavy (the pipeline: mink, scipy)

    live.transport = TransportConfig(ports=PortConfig.free())
    options = SessionOptions(
        task=live.task,
        embodiment=live.embodiment,
        source="quest",
        viser=False,
        headless=True,
        progress=False,
        multiprocess=live.layout == "processes",
        transport=live.transport,
        mirror_hardware=live.mirror,
        hardware_config="emulated" if live.mirror else None,
    )
    fd, live.log_path = tempfile.mkstemp(prefix="beavr_latency_", suffix=".json")
    os.close(fd)
    if live.layout == "single":
        session = SingleProcessSession(options, live.log_path)
    else:
        timing = Attachment(f"{__name__}:attach_twin_timing", live.log_path)
        session = MultiprocessSession(options, attach=(timing,))
    t_start = time.monotonic()
    try:
        session.start()
    except BaseException:
        os.unlink(live.log_path)
        live.log_path = None
        raise
    live.startup_s = time.monotonic() - t_start
    live.session = session


#: Process layouts the harness measures: the ``--multiprocess`` runner (detector, operator
#: and twin processes), or the single-process runner (``python -m beavr_sim.teleop``'s
#: default: the Quest sockets, operator, twin and mirror in one process).
LAYOUTS = ("processes", "single")


def write_latency_log(path, control_hz, applied_log, submit_log, mirror, stage_log) -> None:
    """The twin's timing log as JSON: ``applied`` (t_apply, t_source) per command applied,
    ``stages`` (t_source, t_command, t_take, t_apply) per command, ``submits`` (t_submit,
    {effector: t_source in effect}) per action handed to the mirror, ``links`` (each device's
    write times and hand-off -> write latencies)."""
    links = []
    if mirror is not None:
        for link, effector in zip(mirror.links, mirror._link_effector, strict=True):
            links.append(
                {
                    "name": link.name,
                    "effector": effector,
                    # monotonic time the writer took the tick, and ms from the tick's
                    # hand-off to the first write having left the driver
                    "write_times": list(link.stats.write_times),
                    "write_latency_ms": list(link.stats.write_latency_ms),
                }
            )
    with open(path, "w") as f:
        json.dump(
            {
                "control_hz": control_hz,
                "applied": applied_log,
                "stages": stage_log,
                "submits": submit_log,
                "links": links,
            },
            f,
        )


def attach_twin_timing(process, path: str):
    """The timing log, attached to the twin process's stage (an
    :class:`~beavr_sim.teleop.process_config.Attachment`): every command applied and every action
    handed to the mirror (its hooks run first), written to ``path`` when the process ends."""
    stage, mirror = process.stage, process.mirror
    names = [e.name for e in process.env.embodiment.effectors]
    applied: dict[str, list] = {name: [] for name in names}
    stages: dict[str, list] = {name: [] for name in names}
    submits: list = []
    in_effect: dict[str, float] = {}
    submitted = [False]

    def timing_command(outcome, commands) -> None:
        t_apply = stage.twin.applied_monotonic
        for name in outcome.accepted:
            t_source = float(commands[name].t_source)
            applied[name].append((t_apply, t_source))
            t_command, t_take = process.received.get(name, (float("nan"), float("nan")))
            stages[name].append((t_source, t_command, t_take, t_apply))
            in_effect[name] = t_source
        if mirror is not None:
            submits.append((time.monotonic(), dict(in_effect)))
            submitted[0] = True

    def timing_step(state) -> None:
        if mirror is not None and not submitted[0]:  # the mirror's heartbeat
            submits.append((time.monotonic(), dict(in_effect)))
        submitted[0] = False

    stage.after_command.append(timing_command)
    stage.after_step.append(timing_step)

    def finish() -> None:
        write_latency_log(path, process.env.control_hz, applied, submits, mirror, stages)

    return finish


def single_process_main(options, log_path: str, conn) -> None:
    """The single-process runner (own process, as ``python -m beavr_sim.teleop`` runs it
    without ``--multiprocess``) with the twin's timing log of the multiprocess runner:
    ``applied`` (t_apply, t_source) per command applied, ``submits`` per command handed to
    the mirror, ``links``; runs until the pipe says stop, then sends its counters."""
    import zmq

    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        build_loop,
        start_mirror,
    )

    context = zmq.Context()
    closers: list = []
    loop = build_loop(options, context)
    mirror = start_mirror(options, loop, closers) if options.mirror_hardware else None
    applied: dict[str, list] = {name: [] for name in loop.operator.effectors}
    submits: list = []
    in_effect: dict[str, float] = {}

    def log_command(outcome, commands) -> None:  # after the mirror's hook: it was submitted
        t_apply = loop.twin.applied_monotonic
        for name in outcome.accepted:
            t_source = float(commands[name].t_source)
            applied[name].append((t_apply, t_source))
            in_effect[name] = t_source
        if mirror is not None:
            submits.append((time.monotonic(), dict(in_effect)))

    loop.command_hooks.append(log_command)
    conn.send_bytes(b"ready")
    summary = None
    try:
        summary = loop.run(stop_on_success=False, stop_when=lambda: conn.poll(0.0))
    finally:
        if mirror is not None:
            mirror.close()
        write_latency_log(
            log_path, loop.twin.env.control_hz, applied, submits, mirror, {n: [] for n in applied}
        )
        receiver = loop.source.receiver
        results = {
            "detector": {
                "frames_received": loop.frames_received,
                "frames_rejected": loop.validator.rejected + sum(receiver.rejected.values()),
                "quest_received": dict(receiver.received),
                "frames_superseded": dict(receiver.superseded),
            },
            "operator": {
                "frames_superseded": dict(loop.superseded_by_side),
                "holds": summary.holds if summary is not None else {},
            },
            "twin": {"latency_ms": summary.latency_ms if summary is not None else None},
        }
        for close in reversed(closers):
            close()
        loop.source.close()
        loop.twin.env.close()
        context.term()
        conn.send_bytes(json.dumps(results).encode())


class SingleProcessSession:
    """:func:`single_process_main` in its own process, with the supervisor interface the
    harness uses (``start``, ``dead``, ``stop``, ``results``, ``options``, ``exits``)."""

    def __init__(self, options, log_path: str):
        from beavr_sim.envs.beavr_env import DEFAULT_CONTROL_HZ  # local: heavy (mujoco)

        self.control_hz = DEFAULT_CONTROL_HZ
        self.results: dict = {}
        self.exits: dict = {}
        ctx = mp.get_context("spawn")
        self._pipe, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=single_process_main, args=(options, log_path, child), name="teleop"
        )

    def start(self) -> None:
        self._proc.start()
        if not self._pipe.poll(120.0) or self._pipe.recv_bytes() != b"ready":
            self.stop()
            raise RuntimeError("the single-process runner did not become ready")

    def dead(self) -> list[str]:
        return [] if self._proc.is_alive() else ["teleop"]

    def stop(self) -> None:
        if self._proc.is_alive():
            self._pipe.send_bytes(b"stop")
        if self._pipe.poll(20.0):
            try:
                self.results = json.loads(self._pipe.recv_bytes())
            except (EOFError, ValueError):
                pass
        self._proc.join(10.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(1.0)
        self.exits = {"teleop": self._proc.exitcode}


def drive(lives: list[LiveSession], seconds: float) -> None:
    """Run the load generator for every session at once for ``seconds``; the send times
    land in each ``live.sent``, dead pipeline processes in ``live.died``."""
    rates = {live.rate_hz for live in lives}
    if len(rates) != 1:
        raise ValueError(f"sessions driven together share one headset rate, got {sorted(rates)}")
    ctx = mp.get_context("spawn")
    start_at = time.monotonic() + 1.0 + 0.5 * len(lives)  # time to connect them all
    headsets = []
    for live in lives:
        endpoints = {s: live.transport.endpoint(f"quest_{s}", bind=False) for s in live.streams}
        endpoints["pause"] = live.transport.endpoint("quest_pause", bind=False)
        headsets.append((endpoints, live.payloads, live.duration))
    parent, child = ctx.Pipe()
    args = (headsets, rates.pop(), seconds, child, start_at)
    gen = ctx.Process(target=generator_main, args=args, name="load-generator", daemon=True)
    try:
        gen.start()
        deadline = start_at + seconds + 30.0
        if not parent.poll(max(0.1, deadline - time.monotonic())):
            raise RuntimeError("the load generator did not finish")
        for live, sent in zip(lives, json.loads(parent.recv_bytes()), strict=True):
            live.sent = sent
        time.sleep(0.3)  # the last frames reach the twins
        for live in lives:
            live.died = live.session.dead()
    finally:
        gen.join(5.0)
        if gen.is_alive():
            gen.kill()


def stop_session(live: LiveSession) -> None:
    """Stop ``live``'s pipeline and read its timing log (into ``live.log``)."""
    try:
        live.session.stop()
    finally:
        if live.log_path:
            try:
                with open(live.log_path) as f:
                    live.log = json.load(f)
            except (OSError, ValueError):
                live.log = None
            finally:
                os.unlink(live.log_path)
                live.log_path = None


def session_figures(live: LiveSession, floor_latency: dict) -> dict:
    """Frames, effectors and devices of a stopped session; latency samples (ms) stay under
    each effector's and device's ``"_samples"``."""
    if live.log is None:
        raise RuntimeError(f"{live.embodiment}: the twin wrote no timing log ({live.died})")
    all_sends = [t for ts in live.sent.values() for t in ts]
    window = (min(all_sends) + WARMUP_S, max(all_sends) + 0.3)
    figures = analyse(live.log, live.sent, live.effectors, window, live.rate_hz)
    results = live.session.results
    frames = frame_counts(
        {s: len(ts) for s, ts in live.sent.items()},
        results.get("detector") or results.get("operator", {}).get("detector", {}),
        results.get("operator", {}),
        live.streams,
    )
    for d in figures["effectors"].values():
        d["frames"] = effector_frames(frames, d["side"])
        d["over_floor"] = _over_floor(d["latency_twin_ms"], floor_latency)
    hardware = results.get("twin", {}).get("hardware", {}) or {}
    for name, d in figures["devices"].items():
        d["over_floor"] = _over_floor(d["latency_driver_ms"], floor_latency)
        # the mirror's own account: a failed device makes every device hold (no writes)
        d["errors"] = hardware.get(name, {}).get("errors")
        d["holding"] = hardware.get(name, {}).get("holding")
    return {"frames": frames, **figures}


def _pop_samples(figures: dict, samples: dict | None, prefix: str = "") -> None:
    for group, key in (("effectors", "latency_twin_ms"), ("devices", "latency_driver_ms")):
        for name, d in figures[group].items():
            lat = d.pop("_samples")
            if samples is not None:
                samples[f"{key}_{prefix}{name}"] = lat


def machine_cold_factor(rate_hz: float, seconds: float) -> dict:
    """:func:`beavr_sim.bench.machine.cold_factor` at the headset's frame period: how much
    slower per-frame code runs on this machine once per frame than back to back (about 1 s
    of a 10 s run; fewer repeats for short runs)."""
    gap_ms = 1000.0 / rate_hz
    repeats = int(max(20, min(100, seconds * 1000.0 / gap_ms / 10)))
    return cold_factor(gap_ms, repeats)


def _cold_line(result: dict) -> str:
    cold = result.get("machine", {}).get("cold")
    if not cold:
        return ""
    parts = ", ".join(
        f"{name} {w['hot_us']:.1f} -> {w['after_gap_us']:.1f} us"
        for name, w in cold["workloads"].items()
    )
    return (
        f"machine: the same work after a {cold['gap_ms']:.1f} ms gap is x{cold['factor']} "
        f"slower than back to back ({parts}); near 1 on a dedicated core"
    )


def run(
    config: int = 1,
    seconds: float = 10.0,
    mirror: bool = True,
    floor_seconds: float | None = None,
    samples: dict | None = None,
    layout: str = "processes",
) -> dict:
    """Measure configuration ``config`` for ``seconds`` of stream in process ``layout`` (one
    of :data:`LAYOUTS`); the result dict."""
    embodiment, rate_hz, task = CONFIGS[config]
    live = prepare(embodiment, task, rate_hz, mirror, layout)
    # The floor first, on the same machine with nothing of ours running (run after the
    # pipeline it catches the processes' shutdown).
    floor = transport_floor(_max_payload([live]), rate_hz, floor_seconds or min(seconds, 5.0))
    floor_samples = floor.pop("samples_ms")
    cold = machine_cold_factor(rate_hz, seconds)
    start_session(live)
    try:
        drive([live], seconds)
    finally:
        stop_session(live)
    figures = session_figures(live, floor["latency_ms"])
    _pop_samples(figures, samples)
    if samples is not None:
        samples["floor_ms"] = floor_samples
    session = live.session
    return {
        "benchmark": "latency",
        "config": config,
        "layout": layout,
        "embodiment": embodiment,
        "task": task,
        "headset_hz": rate_hz,
        "target_hz": rate_hz,
        "control_hz": live.log["control_hz"],
        "operator_hz": session.control_hz,
        "seconds": seconds,
        "warmup_s": WARMUP_S,
        "startup_s": round(live.startup_s, 2),
        "mirror_hardware": mirror,
        "hardware_config": "emulated" if mirror else None,
        "processes_died": live.died,
        "exits": session.exits,
        **figures,
        "floor": floor,
        "twin_latency_ms_own": session.results.get("twin", {}).get("latency_ms"),
        # commands that held (not applied, so not in the rates): effector -> reason -> n
        "operator_holds": session.results.get("operator", {}).get("holds", {}),
        "beavr_table_v": BEAVR_TABLE_V,
        "machine": {"cpus": os.cpu_count(), "platform": sys.platform, "cold": cold},
    }


def sweep_sessions(n_effectors: int) -> list[str]:
    """The embodiments run concurrently for ``n_effectors`` hand effectors (at most two per
    embodiment): one right arm for 1, else bimanual pairs (plus a right arm when odd)."""
    if n_effectors < 1:
        raise ValueError(f"effector count must be >= 1, got {n_effectors}")
    pairs, single = divmod(n_effectors, 2)
    return ["xarm7_leap_right"] * single + ["xarm7_leap_bimanual"] * pairs


def sweep_point(sessions: list[dict], floor_latency: dict) -> dict:
    """One effector count of the sweep from the :func:`session_figures` of its concurrent
    sessions (each with ``"embodiment"``, ``"startup_s"`` and ``"processes_died"`` added;
    the ``"_samples"`` still in): send -> twin and send -> driver pooled over all effectors
    (devices driven by them) of all sessions."""
    twin = [x for s in sessions for d in s["effectors"].values() for x in d["_samples"]]
    driver = [x for s in sessions for d in s["devices"].values() for x in d["_samples"]]
    effs = {f"s{i}.{n}": d for i, s in enumerate(sessions) for n, d in s["effectors"].items()}
    devs = [d for s in sessions for d in s["devices"].values() if d["repeats"] is not None]
    pcts = [d["pct_of_target"] for d in effs.values()]
    write_pcts = [d["pct_of_target"] for d in devs]
    twin_stats, driver_stats = _stats(twin), _stats(driver)

    def total(key):
        return sum(
            v for s in sessions for v in s["frames"][key].values() if isinstance(v, (int, float))
        )

    rejected = [s["frames"]["rejected"] for s in sessions]
    return {
        "effectors": len(effs),
        "sessions": len(sessions),
        "embodiments": [s["embodiment"] for s in sessions],
        "startup_s": [s["startup_s"] for s in sessions],
        "processes_died": [
            f"s{i}:{p}" for i, s in enumerate(sessions) for p in s["processes_died"]
        ],
        "device_errors": [
            f"s{i}.{n}"
            for i, s in enumerate(sessions)
            for n, d in s["devices"].items()
            if d.get("errors")
        ],
        "send_to_twin_ms": twin_stats,
        "send_to_driver_ms": driver_stats,
        "over_floor": {
            "send_to_twin": _over_floor(twin_stats, floor_latency),
            "send_to_driver": _over_floor(driver_stats, floor_latency),
        },
        "pct_of_target_min": min((p or 0.0 for p in pcts), default=None),
        "write_pct_of_target_min": min((p or 0.0 for p in write_pcts), default=None),
        "repeats": sum(d["repeats"] for d in effs.values()),
        "frames": {
            "sent": total("sent"),
            "dropped": total("dropped"),
            "superseded": total("superseded_total"),
            "rejected": sum(r for r in rejected if isinstance(r, int)),
        },
        "per_effector": {
            n: {
                "command_hz": d["command_hz"],
                "pct_of_target": d["pct_of_target"],
                "repeats": d["repeats"],
                "p50": d["latency_twin_ms"]["p50"],
                "p99": d["latency_twin_ms"]["p99"],
            }
            for n, d in effs.items()
        },
    }


def sweep_growth(points: list[dict], lo: int = 1, hi: int = 4) -> dict:
    """p99 at ``hi`` effectors / p99 at ``lo``, send -> twin and send -> driver, against
    :data:`SWEEP_P99_GROWTH_TARGET` (None where a count is missing or has no samples)."""
    by_n = {p["effectors"]: p for p in points}
    growth = {}
    for key in ("send_to_twin", "send_to_driver"):
        a = by_n.get(lo, {}).get(f"{key}_ms", {}).get("p99")
        b = by_n.get(hi, {}).get(f"{key}_ms", {}).get("p99")
        growth[key] = round(b / a, 2) if a and b is not None else None
    known = [g for g in growth.values() if g is not None]
    return {
        "from": lo,
        "to": hi,
        **growth,
        "target": SWEEP_P99_GROWTH_TARGET,
        "within_target": all(g <= SWEEP_P99_GROWTH_TARGET for g in known) if known else None,
    }


def run_sweep(
    counts=SWEEP_COUNTS,
    seconds: float = 10.0,
    mirror: bool = True,
    floor_seconds: float | None = None,
    samples: dict | None = None,
) -> dict:
    """``--sweep``: for each effector count, its sessions (:func:`sweep_sessions`) started one
    after the other, driven concurrently at :data:`SWEEP_HZ` for ``seconds``, stopped, and
    analysed; pooled per count (:func:`sweep_point`). All sessions of a count share this
    machine's cores. ``samples`` gets ``sweep_twin_ms_<n>`` / ``sweep_driver_ms_<n>``."""
    counts = [int(n) for n in counts]
    plan = {n: sweep_sessions(n) for n in counts}
    every = [
        prepare(e, SWEEP_TASK, SWEEP_HZ, mirror)
        for e in sorted({e for p in plan.values() for e in p})
    ]
    floor = transport_floor(_max_payload(every), SWEEP_HZ, floor_seconds or min(seconds, 5.0))
    floor_samples = floor.pop("samples_ms")
    cold = machine_cold_factor(SWEEP_HZ, seconds)
    points = []
    for n in counts:
        lives = [prepare(e, SWEEP_TASK, SWEEP_HZ, mirror) for e in plan[n]]
        started = []
        try:
            for live in lives:
                start_session(live)
                started.append(live)
            drive(lives, seconds)
        finally:
            for live in started:
                stop_session(live)
        sessions = []
        for live in lives:
            figures = session_figures(live, floor["latency_ms"])
            figures.update(
                embodiment=live.embodiment,
                startup_s=round(live.startup_s, 2),
                processes_died=live.died,
            )
            sessions.append(figures)
        point = sweep_point(sessions, floor["latency_ms"])
        point["control_hz"] = lives[0].log["control_hz"]
        points.append(point)
        if samples is not None:
            for group, kind in (("effectors", "twin"), ("devices", "driver")):
                samples[f"sweep_{kind}_ms_{n}"] = [
                    x for s in sessions for d in s[group].values() for x in d["_samples"]
                ]
    if samples is not None:
        samples["floor_ms"] = floor_samples
    cpus = os.cpu_count()
    return {
        "benchmark": "latency_sweep",
        "task": SWEEP_TASK,
        "headset_hz": SWEEP_HZ,
        "target_hz": SWEEP_HZ,
        "seconds": seconds,
        "warmup_s": WARMUP_S,
        "mirror_hardware": mirror,
        "hardware_config": "emulated" if mirror else None,
        "counts": counts,
        "shared_cores": f"all sessions of a count (pipelines, generators, emulated rigs) share "
        f"this machine's {cpus} cores",
        "floor": floor,
        "sweep": points,
        "p99_growth_1_to_4": sweep_growth(points),
        "machine": {"cpus": cpus, "platform": sys.platform, "cold": cold},
    }


def _f(x, spec: str = ".2f") -> str:
    return "-" if x is None else format(x, spec)


_HEADER = (
    f"{'':28}{'rate Hz':>9}{'% tgt':>8}{'jitter':>8}{'p50':>8}{'p95':>8}{'p99':>8}"
    f"{'max':>8}{'n':>6}{'rep':>6}{'/floor p50':>11}{'p99':>6}"
)


def _row(label, hz, pct, jit, lat, over, repeats=None) -> str:
    over = over or {}
    return (
        f"{label:28}{_f(hz, '.2f'):>9}{_f(pct, '.1f'):>8}{_f(jit, '.2f'):>8}"
        f"{_f(lat['p50']):>8}{_f(lat['p95']):>8}{_f(lat['p99']):>8}{_f(lat['max']):>8}"
        f"{lat['n']:>6}{_f(repeats, 'd'):>6}{_f(over.get('p50'), '.1f'):>11}"
        f"{_f(over.get('p99'), '.1f'):>6}"
    )


def table(result: dict) -> str:
    """The human-readable report."""
    r = result
    fr = r["frames"]
    lines = [
        f"latency, config {r['config']} ({r.get('layout', 'processes')}): {r['embodiment']} "
        f"({r['task']}), headset "
        f"{r['headset_hz']:g} Hz (= target rate), a command per frame, twin physics "
        f"{r['control_hz']:g} Hz, {r['seconds']:g} s, mirroring "
        f"{'emulated' if r['mirror_hardware'] else 'off'}",
        f"frames sent {fr['sent']}, received {fr['received']}, dropped {fr['dropped']}, "
        f"passed on {fr['passed_on']}, superseded {fr['superseded_total']} (detector "
        f"{fr['superseded']}, operator {fr['superseded_operator']}), rejected {fr['rejected']}",
        f"operator holds (commands not applied, not in the rates): {r.get('operator_holds', {})}",
        _HEADER,
    ]
    for name, d in r["effectors"].items():
        lines.append(
            _row(
                f"{name}: send->twin",
                d["command_hz"],
                d["pct_of_target"],
                d["jitter_ms"].get("std_ms"),
                d["latency_twin_ms"],
                d["over_floor"],
                d["repeats"],
            )
        )
        lines.append(
            _row(
                f"{name}:  send->detector",
                None,
                None,
                (d.get("send_jitter_ms") or {}).get("std_ms"),
                d["send_to_detector_ms"],
                None,
            )
        )
        for stage, label in (
            ("detector_to_operator_command", "  detector->operator"),
            ("operator_command_to_twin", "  operator->twin"),
            ("twin_guard_and_apply", "  twin guard+apply"),
        ):
            stats = d.get("stages_ms", {}).get(stage)
            if stats and stats["n"]:
                lines.append(_row(f"{name}:{label}", None, None, None, stats, None))
    for name, d in r["devices"].items():
        lines.append(
            _row(
                f"{name}: send->driver",
                d["write_hz"],
                d["pct_of_target"],
                d["jitter_ms"].get("std_ms"),
                d["latency_driver_ms"],
                d["over_floor"],
                d["repeats"],
            )
        )
    failed = {n: d["holding"] for n, d in r["devices"].items() if d.get("errors")}
    if failed:
        lines.append(f"devices failed (every device then holds): {failed}")
    fl = r["floor"]
    lines.append(_row("floor: bare ZMQ hop", fl["rate_hz"], None, None, fl["latency_ms"], None))
    if _cold_line(r):
        lines.append(_cold_line(r))
    lines.append(
        "latencies in ms; rates over distinct commands (writes), % of the headset rate; jitter = "
        "std of the interval between them (ms; on the send->detector row: between the load "
        "generator's own sends, the input's jitter); rep = repeats (same t_source), left out"
    )
    return "\n".join(lines)


def sweep_table(result: dict) -> str:
    """The ``--sweep`` report."""
    r = result
    lines = [
        f"latency sweep: {r['task']}, headset {r['headset_hz']:g} Hz, {r['seconds']:g} s per "
        f"count, mirroring {'emulated' if r['mirror_hardware'] else 'off'}; "
        f"{r['shared_cores']}",
        f"{'effectors':>10}{'sessions':>9}{'min % tgt':>10}{'twin p50':>10}{'p99':>8}"
        f"{'driver p50':>11}{'p99':>8}{'twin p99/floor':>15}{'dropped':>8}{'died':>6}{'dev err':>8}",
    ]
    for p in r["sweep"]:
        tw, dr = p["send_to_twin_ms"], p["send_to_driver_ms"]
        lines.append(
            f"{p['effectors']:>10}{p['sessions']:>9}{_f(p['pct_of_target_min'], '.1f'):>10}"
            f"{_f(tw['p50']):>10}{_f(tw['p99']):>8}{_f(dr['p50']):>11}{_f(dr['p99']):>8}"
            f"{_f(p['over_floor']['send_to_twin']['p99'], '.1f'):>15}"
            f"{p['frames']['dropped']:>8}{len(p['processes_died']):>6}"
            f"{len(p.get('device_errors', [])):>8}"
        )
    fl = r["floor"]["latency_ms"]
    g = r["p99_growth_1_to_4"]
    lines.append(
        f"floor (bare ZMQ hop, {r['headset_hz']:g} Hz): p50 {_f(fl['p50'])}, p99 {_f(fl['p99'])}"
    )
    lines.append(
        f"p99 growth {g['from']} -> {g['to']} effectors: send->twin {_f(g['send_to_twin'])}x, "
        f"send->driver {_f(g['send_to_driver'])}x (target <= {g['target']:g}x)"
    )
    if _cold_line(r):
        lines.append(_cold_line(r))
    lines.append(
        "latencies in ms, pooled over all effectors (devices) of all sessions of a count; dev "
        "err: devices the mirror saw fail (then every device of that rig holds: no writes)"
    )
    return "\n".join(lines)


def finite_positive(stats: dict) -> bool:
    return all(
        stats[q] is not None and math.isfinite(stats[q]) and stats[q] > 0
        for q in ("p50", "p95", "p99", "max")
    )
