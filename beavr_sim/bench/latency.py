"""``python -m beavr_sim.bench latency``: the ``--multiprocess`` pipeline's end-to-end latency,
measured as the BEAVR paper's Table V (issue 20).

A load generator process speaks the BEAVR Quest app's wire protocol: it PUSHes keypoint
strings (``format_keypoints`` of a bundled human-hand trace, looped at real speed) to the
detector's Quest PULL ports at the headset rate, one per hand the embodiment uses, and the
pause status ``High`` with each app frame. The pipeline under test is the ``--multiprocess``
runner as it is (detector, operator and twin processes over loopback ZeroMQ), mirroring to the
emulated hardware (``hardware_config="emulated"``), started with a timing log
(``options["latency_log"]``, written by the twin process; see ``processes.py``).

What each number spans (all clocks are ``time.monotonic`` on one machine):

- ``latency_twin_ms``: generator send (just before ``socket.send`` of the keypoint string) ->
  the command derived from it handed to the twin's actuators (``TwinInterface.apply``). The
  frame behind a command is found from the command's ``t_source``, the detector's receive
  stamp of the newest frame the operator had used: its send is the generator's latest send on
  that hand's stream at or before that stamp (the detector takes the newest payload of each
  poll, so that is the frame it parsed). Only the first application of each frame counts.
- ``latency_driver_ms``: generator send -> the emulated device's driver call that wrote the
  first target derived from it having returned (hardware mirror writer thread). The write's
  time is its tick's hand-off to the mirror plus the mirror's measured hand-off -> write time.
- ``send_to_detector_ms``: generator send -> the detector's receive stamp (transport plus the
  detector's 2 ms polling); ``detector_to_twin_ms``: the rest (what the twin's own
  ``latency_ms`` reports).
- ``command_hz``: commands applied to the twin per second for the effector (hold ticks
  excluded) against ``target_hz`` (the twin's control rate); ``jitter_ms``: standard deviation
  of the interval between successive applied commands (and driver writes, per device).
- ``floor``: a bare ZeroMQ PUSH -> PULL hop on loopback with a keypoint string of the same
  size at the same rate (sender in its own process, blocking receiver), run just before the
  pipeline in the same invocation.

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

import numpy as np

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
    from beavr_sim.assets import bundled_trace
    from beavr_sim.headset.quest_protocol import format_keypoints
    from beavr_sim.traces.format import TraceReader

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


def generator_main(
    endpoints: dict, payloads: dict, duration: float, rate_hz: float, seconds: float, conn
) -> None:
    """The load generator (own process): sends for ``seconds`` at ``rate_hz``; its send times
    per side go back through the pipe ``conn``."""
    import zmq

    context = zmq.Context()
    socks = {}
    for name, endpoint in endpoints.items():
        s = context.socket(zmq.PUSH)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, 1000)
        s.connect(endpoint)
        socks[name] = s
    time.sleep(0.3)  # the connections are up before the first frame
    sent: dict[str, list[float]] = {s: [] for s in payloads}
    period = 1.0 / rate_hz
    start = time.monotonic()
    k = 0
    while True:
        t_due = start + k * period
        if t_due - start >= seconds:
            break
        delay = t_due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        trace_t = ((time.monotonic() - start) % duration) if duration > 0 else 0.0
        for side, (times, data) in payloads.items():
            i = min(int(np.searchsorted(times, trace_t, side="right")) - 1, len(data) - 1)
            payload = data[max(0, i)]
            t_send = time.monotonic()
            socks[side].send(payload)
            sent[side].append(t_send)
        if "pause" in socks:
            socks["pause"].send(b"High")
        k += 1
    conn.send_bytes(json.dumps(sent).encode())
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

    from beavr_sim.wire.ports import free_tcp_ports

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


def _rate(times, window: tuple[float, float]) -> tuple[float | None, dict]:
    t = np.asarray([x for x in times if window[0] <= x <= window[1]], dtype=float)
    if t.size < 2:
        return None, _stats([])
    intervals = np.diff(t) * 1e3
    hz = (t.size - 1) / (t[-1] - t[0])
    return float(hz), {
        "std_ms": round(float(intervals.std()), 4),
        "mean_ms": round(float(intervals.mean()), 4),
        **{k: v for k, v in _stats(intervals).items() if k in ("p99", "max")},
    }


def analyse(log: dict, sent: dict, sides: dict[str, str], window: tuple[float, float]) -> dict:
    """Per effector figures from the twin's timing log and the generator's send times;
    ``sides``: effector -> the hand stream that drives it."""
    target_hz = float(log["control_hz"])
    effectors = {}
    for name, side in sides.items():
        sends = np.asarray(sent[side], dtype=float)
        applied = [(t, ts) for t, ts in log["applied"].get(name, []) if window[0] <= t <= window[1]]
        hz, jitter = _rate([t for t, _ in applied], window)
        fresh, seen = [], set()
        for t_apply, t_source in applied:
            if t_source > 0 and t_source not in seen:
                seen.add(t_source)
                fresh.append((t_apply, t_source))
        idx = _latest_send(sends, [ts for _, ts in fresh])
        twin_ms, det_ms, rest_ms = [], [], []
        for (t_apply, t_source), i in zip(fresh, idx, strict=True):
            if i >= 0:
                twin_ms.append((t_apply - sends[i]) * 1e3)
                det_ms.append((t_source - sends[i]) * 1e3)
                rest_ms.append((t_apply - t_source) * 1e3)
        effectors[name] = {
            "side": side,
            "target_hz": target_hz,
            "command_hz": round(hz, 3) if hz else None,
            "pct_of_target": round(100 * hz / target_hz, 2) if hz else None,
            "commands_applied": len(applied),
            "fresh_frames_applied": len(fresh),
            "jitter_ms": jitter,
            "latency_twin_ms": _stats(twin_ms),
            "send_to_detector_ms": _stats(det_ms),
            "detector_to_twin_ms": _stats(rest_ms),
            "_samples": twin_ms,
        }
    submits = log.get("submits", [])
    submit_t = np.asarray([t for t, _ in submits], dtype=float)
    devices = {}
    for link in log.get("links", []):
        name, effector = link["name"], link["effector"]
        side = sides.get(effector)
        sends = np.asarray(sent.get(side, []), dtype=float)
        write_times = link["write_times"]
        hz, jitter = _rate(write_times, window)
        lat, last = [], None
        for t_take, w_ms in zip(write_times, link["write_latency_ms"], strict=False):
            if not window[0] <= t_take <= window[1]:
                continue
            k = int(np.searchsorted(submit_t, t_take, side="right")) - 1
            if k < 0:
                continue
            t_sub, in_effect = submits[k]
            t_source = in_effect.get(effector, 0.0)
            if t_source <= 0 or t_source == last:
                continue
            last = t_source
            i = int(_latest_send(sends, [t_source])[0])
            if i >= 0:
                lat.append((t_sub + w_ms / 1e3 - sends[i]) * 1e3)
        devices[name] = {
            "effector": effector,
            "target_hz": target_hz,
            "write_hz": round(hz, 3) if hz else None,
            "pct_of_target": round(100 * hz / target_hz, 2) if hz else None,
            "jitter_ms": jitter,
            "latency_driver_ms": _stats(lat),
            "_samples": lat,
        }
    return {"effectors": effectors, "devices": devices}


def run(
    config: int = 1,
    seconds: float = 10.0,
    mirror: bool = True,
    floor_seconds: float | None = None,
    samples: dict | None = None,
) -> dict:
    """Measure configuration ``config`` for ``seconds`` of stream; the result dict."""
    from beavr_sim.robots import make_embodiment
    from beavr_sim.teleop.processes import MultiprocessSession
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    embodiment, rate_hz, task = CONFIGS[config]
    effectors = {e.name: e.side for e in make_embodiment(embodiment).effectors}
    streams = sorted(set(effectors.values()))
    payloads, duration = _hand_payloads(embodiment, task, streams)
    # The floor first, on the same machine with nothing of ours running (run after the
    # pipeline it catches the processes' shutdown).
    payload = max((p for _, ps in payloads.values() for p in ps), key=len)
    floor = transport_floor(payload, rate_hz, floor_seconds or min(seconds, 5.0))
    transport = TransportConfig(ports=PortConfig.free())
    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="quest",
        viser=False,
        headless=True,
        progress=False,
        multiprocess=True,
        transport=transport,
        mirror_hardware=mirror,
        hardware_config="emulated" if mirror else None,
    )
    session = MultiprocessSession(options)
    fd, log_path = tempfile.mkstemp(prefix="beavr_latency_", suffix=".json")
    os.close(fd)
    session.options["latency_log"] = log_path
    t_start = time.monotonic()
    session.start()
    startup_s = time.monotonic() - t_start
    endpoints = {s: transport.endpoint(f"quest_{s}", bind=False) for s in streams}
    endpoints["pause"] = transport.endpoint("quest_pause", bind=False)
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    gen = ctx.Process(
        target=generator_main,
        args=(endpoints, payloads, duration, rate_hz, seconds, child),
        name="load-generator",
        daemon=True,
    )
    died: list[str] = []
    try:
        gen.start()
        if not parent.poll(seconds + 30.0):
            raise RuntimeError("the load generator did not finish")
        sent = json.loads(parent.recv_bytes())
        time.sleep(0.3)  # the last frames reach the twin
        died = session.dead()
    finally:
        gen.join(5.0)
        if gen.is_alive():
            gen.kill()
        session.stop()
    try:
        with open(log_path) as f:
            log = json.load(f)
    finally:
        os.unlink(log_path)
    all_sends = [t for ts in sent.values() for t in ts]
    window = (min(all_sends) + WARMUP_S, max(all_sends) + 0.3)
    figures = analyse(log, sent, effectors, window)
    det = session.results.get("detector", {})
    frames = {
        "sent": {s: len(ts) for s, ts in sent.items()},
        "received": {s: det.get("quest_received", {}).get(s, 0) for s in streams},
        "passed_on": det.get("frames_received", 0),
        "superseded": det.get("frames_superseded", {}),
        "rejected": det.get("frames_rejected", 0),
        "rejected_by_reason": det.get("rejected_by_reason", {}),
    }
    floor_samples = floor.pop("samples_ms")
    fl = floor["latency_ms"]
    for group, key in (("effectors", "latency_twin_ms"), ("devices", "latency_driver_ms")):
        for name, d in figures[group].items():
            lat = d[key]
            d["over_floor"] = {
                q: round(lat[q] / fl[q], 1) if lat[q] and fl[q] else None for q in ("p50", "p99")
            }
            if samples is not None:
                samples[f"{key}_{name}"] = d["_samples"]
            del d["_samples"]
    if samples is not None:
        samples["floor_ms"] = floor_samples
    twin = session.results.get("twin", {})
    return {
        "benchmark": "latency",
        "config": config,
        "embodiment": embodiment,
        "task": task,
        "headset_hz": rate_hz,
        "control_hz": log["control_hz"],
        "operator_hz": session.options["control_hz"],
        "seconds": seconds,
        "warmup_s": WARMUP_S,
        "startup_s": round(startup_s, 2),
        "mirror_hardware": mirror,
        "hardware_config": "emulated" if mirror else None,
        "processes_died": died,
        "exits": session.exits,
        "frames": frames,
        "effectors": figures["effectors"],
        "devices": figures["devices"],
        "floor": floor,
        "twin_latency_ms_own": twin.get("latency_ms"),
        "beavr_table_v": BEAVR_TABLE_V,
        "machine": {"cpus": os.cpu_count(), "platform": sys.platform},
    }


def _f(x, spec: str = ".2f") -> str:
    return "-" if x is None else format(x, spec)


def table(result: dict) -> str:
    """The human-readable report."""
    r = result
    fr = r["frames"]
    lines = [
        f"latency, config {r['config']}: {r['embodiment']} ({r['task']}), headset "
        f"{r['headset_hz']:g} Hz, operator {r['operator_hz']:g} Hz, twin {r['control_hz']:g} Hz, "
        f"{r['seconds']:g} s, mirroring {'emulated' if r['mirror_hardware'] else 'off'}",
        f"frames sent {fr['sent']}, received {fr['received']}, passed on {fr['passed_on']}, "
        f"superseded {fr['superseded']}, rejected {fr['rejected']}",
        f"{'':26}{'rate Hz':>9}{'% tgt':>8}{'jitter':>8}{'p50':>8}{'p95':>8}{'p99':>8}"
        f"{'max':>8}{'n':>6}{'/floor p50':>11}",
    ]

    def row(label, hz, pct, jit, lat, over):
        lines.append(
            f"{label:26}{_f(hz, '.2f'):>9}{_f(pct, '.1f'):>8}{_f(jit, '.2f'):>8}"
            f"{_f(lat['p50']):>8}{_f(lat['p95']):>8}{_f(lat['p99']):>8}{_f(lat['max']):>8}"
            f"{lat['n']:>6}{_f(over.get('p50') if over else None, '.1f'):>11}"
        )

    for name, d in r["effectors"].items():
        row(
            f"{name}: send->twin",
            d["command_hz"],
            d["pct_of_target"],
            d["jitter_ms"].get("std_ms"),
            d["latency_twin_ms"],
            d["over_floor"],
        )
        row(f"{name}:  send->detector", None, None, None, d["send_to_detector_ms"], None)
    for name, d in r["devices"].items():
        row(
            f"{name}: send->driver",
            d["write_hz"],
            d["pct_of_target"],
            d["jitter_ms"].get("std_ms"),
            d["latency_driver_ms"],
            d["over_floor"],
        )
    row("floor: bare ZMQ hop", r["floor"]["rate_hz"], None, None, r["floor"]["latency_ms"], None)
    lines.append("latencies in ms; jitter = std of the interval between commands (ms)")
    return "\n".join(lines)


def finite_positive(stats: dict) -> bool:
    return all(
        stats[q] is not None and math.isfinite(stats[q]) and stats[q] > 0
        for q in ("p50", "p95", "p99", "max")
    )
