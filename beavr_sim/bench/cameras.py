"""``python -m beavr_sim.bench cameras``: two real cameras recorded in lockstep, what they cost.

The paper's set-up: two 480x640 cameras at 30 fps, recorded at 30 Hz. The cameras are LeRobot's
own ZMQ camera class fed with synthetic frames, each from a local image server (LeRobot's ZMQ
protocol, JPEG, in a child process as a camera host would be); not OpenCV video files: LeRobot's
OpenCV camera reads a file as fast as it decodes, so a file is no 30 fps camera. The
control loop ticks at ``--fps``: one env step (the Playground twin) and, with cameras, a grab
of both cameras' newest frames copied as the recorder copies them. Three conditions run
interleaved (``--runs`` rounds of ``--seconds`` each): ``none`` (no cameras connected),
``cameras``, ``cameras+stream`` (the camera stream at ``--stream-hz`` encoding JPEG panels
for a viewer, reading the cameras on its own thread as a session's does) and
``cameras+stream+twin`` (the same in the ``both`` view: the tick copies the twin's pose for a
``TwinCameraFeed``, the stream's thread renders the twin's ``front`` at 480x640 per camera).
Reported per condition as ranges over the rounds:
the tick's work time p50 / p99 (ms), the loop's rate, the recording's achieved rate (frames with every
camera live per second) and grabs with a camera dead, capture-to-record age p50 / p99 (ms), stale and repeated frames. JSON on the
last stdout line. Figures: docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import base64
import json
import multiprocessing as mp
import sys
import time

import cv2
import gymnasium as gym
import numpy as np

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.cameras.stream import CameraStream, StreamConfig, StreamFrame

CONDITIONS = ("none", "cameras", "cameras+stream", "cameras+stream+twin")
HEIGHT, WIDTH = 480, 640


def _frame(i: int, name_index: int) -> np.ndarray:
    """A synthetic 480x640 scene with texture (a JPEG of it costs what a camera's does)."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    image = np.stack(
        [(x + 3 * i) % 256, (y + 2 * i + 40 * name_index) % 256, (x + y + i) % 256], axis=-1
    ).astype(np.uint8)
    return image


def _serve(port_queue, stop, name: str, index: int, fps: float) -> None:
    """A LeRobot ZMQ image server (child process): JSON {timestamps, images} on PUB."""
    import zmq

    context = zmq.Context()
    socket = context.socket(zmq.PUB)
    socket.setsockopt(zmq.SNDHWM, 2)
    port_queue.put(socket.bind_to_random_port("tcp://127.0.0.1"))
    frames = [cv2.imencode(".jpg", _frame(i, index))[1].tobytes() for i in range(30)]
    period, next_at, i = 1.0 / fps, time.perf_counter(), 0
    while not stop.is_set():
        message = {
            "timestamps": {name: time.time()},
            "images": {name: base64.b64encode(frames[i % len(frames)]).decode()},
        }
        socket.send_string(json.dumps(message))
        i += 1
        next_at += period
        time.sleep(max(0.0, next_at - time.perf_counter()))
    socket.close(linger=0)
    context.term()


class _Servers:
    def __init__(self, names: tuple[str, ...], fps: float) -> None:
        ctx = mp.get_context("spawn")
        self.stop = ctx.Event()
        queue = ctx.Queue()
        self.procs = [
            ctx.Process(target=_serve, args=(queue, self.stop, n, i, fps), daemon=True)
            for i, n in enumerate(names)
        ]
        for p in self.procs:
            p.start()
        self.ports = [queue.get(timeout=60) for _ in self.procs]

    def close(self) -> None:
        self.stop.set()
        for p in self.procs:
            p.join(timeout=5)


def _configs(names, fps: float, ports):
    from beavr_sim.cameras.spec import parse_camera_table  # local: heavy (lerobot + torch, ~1 s)

    return {
        name: parse_camera_table(
            name,
            {
                "type": "zmq",
                "server_address": "127.0.0.1",
                "port": ports[i],
                "fps": int(fps),
                "width": WIDTH,
                "height": HEIGHT,
            },
        )
        for i, name in enumerate(names)
    }


def _round(condition: str, args, env, action, ports) -> dict:
    from beavr_sim.cameras.real import RealCameras  # local: heavy (lerobot + torch, ~1 s)
    from beavr_sim.teleop.twin_camera_feed import TwinCameraFeed  # local: heavy (mujoco GL)

    names = ("front", "overhead")
    cameras = stream = feed = None
    if condition != "none":
        configs = _configs(names, args.fps, ports)
        cameras = RealCameras(configs, control_period_s=1.0 / args.fps)
        cameras.connect()
        if condition.startswith("cameras+stream"):
            sent = [0]

            def viewer(frame: StreamFrame) -> None:  # what a WebXR page's sink does
                cv2.imencode(".jpg", frame.image)
                sent[0] += 1

            shapes = {n: cameras.frame_shape(n) for n in names}
            view = "real"
            if condition.endswith("+twin"):
                twin_env = env.unwrapped
                feed = TwinCameraFeed(twin_env.render_model, twin_env.data, "front", args.stream_hz)
                view = "both"
            stream = CameraStream(
                StreamConfig(rate_hz=args.stream_hz, view=view),
                [viewer],
                shapes,
                source=cameras.peek,
                twin=feed,
            )
    period = 1.0 / args.fps
    work, recorded, dead = [], 0, 0
    start = next_at = time.perf_counter()
    end = start + args.seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        env.step(action)
        if feed is not None:
            feed(None)  # the tick listener's pose copy (when one is due)
        if cameras is not None:
            grab = cameras.grab()
            if not grab.dead:
                frames = {n: f.copy() for n, f in grab.frames.items()}  # as the recorder stores
                recorded += 1
                del frames
            else:
                dead += 1
        else:
            recorded += 1
        work.append(time.perf_counter() - t0)
        next_at += period
        time.sleep(max(0.0, next_at - time.perf_counter()))
    elapsed = time.perf_counter() - start
    out = {
        "tick_p50_ms": float(np.percentile(work, 50)) * 1e3,
        "tick_p99_ms": float(np.percentile(work, 99)) * 1e3,
        "loop_hz": len(work) / elapsed,
        "rate_hz": recorded / elapsed,
        "dead_grabs": dead,
    }
    if cameras is not None:
        summary = cameras.summary()
        out |= {
            "age_p50_ms": max(s["age_p50_ms"] for s in summary.values()),
            "age_p99_ms": max(s["age_p99_ms"] for s in summary.values()),
            "stale": sum(s["stale"] for s in summary.values()),
            "repeats": sum(s["repeats"] for s in summary.values()),
        }
        cameras.close()
    if stream is not None:
        stream.close()
        out["stream_sent"] = stream.sent
        out["stream_dropped"] = stream.dropped
        out["twin_renders"] = stream.twin_renders
    return out


def _ranges(rounds: list[dict]) -> dict:
    keys = rounds[0].keys()
    return {
        k: [round(min(r[k] for r in rounds), 2), round(max(r[k] for r in rounds), 2)] for k in keys
    }


def run(args) -> dict:
    env = gym.make("beavr_sim/Playground-v0")
    env.reset(seed=0)
    action = np.asarray(env.action_space.sample() * 0, dtype=np.float64)
    servers = _Servers(("front", "overhead"), args.fps)
    results: dict[str, list[dict]] = {c: [] for c in CONDITIONS}
    try:
        for _ in range(args.runs):
            for condition in CONDITIONS:  # interleaved
                results[condition].append(_round(condition, args, env, action, servers.ports))
                print(f"{condition}: {results[condition][-1]}", file=sys.stderr)
    finally:
        servers.close()
        env.close()
    return {
        "benchmark": "cameras",
        "source": "zmq image servers (child processes)",
        "cameras": f"2 x {HEIGHT}x{WIDTH} @ {args.fps:g} fps",
        "fps": args.fps,
        "seconds": args.seconds,
        "runs": args.runs,
        "stream_hz": args.stream_hz,
        "conditions": {c: _ranges(r) for c, r in results.items()},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.bench cameras", description=__doc__)
    parser.add_argument("--fps", type=float, default=30.0, help="cameras and recording (30)")
    parser.add_argument("--seconds", type=float, default=5.0, help="per round (5)")
    parser.add_argument("--runs", type=int, default=3, help="interleaved rounds (3)")
    parser.add_argument("--stream-hz", type=float, default=5.0, help="camera stream rate (5)")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.seconds <= 0 or args.fps <= 0:
        parser.error("--runs must be >= 1, --seconds and --fps > 0")
    print(json.dumps(run(args)))
    return 0
