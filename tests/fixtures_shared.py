"""Test helpers several test files share (imported as ``from fixtures_shared import ...``:
``tests/`` is on the path, as for ``waiting.py``)."""

from __future__ import annotations

import base64
import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import zmq


def cut_bundled_trace(out: Path, seconds: float, task: str = "PickupBox") -> Path:
    """The task's bundled trace cut after ``seconds`` of hand frames, written to ``out``."""
    from beavr_sim.assets import bundled_trace
    from beavr_sim.traces.format import TraceReader, TraceWriter

    reader = TraceReader(bundled_trace(task))
    with TraceWriter(out, reader.metadata) as writer:
        t0 = None
        for _t, kind, payload in reader.events():
            if kind == "hand":
                t0 = payload.t_source if t0 is None else t0
                if payload.t_source - t0 <= seconds:
                    writer.write_hand(payload)
    return out


class ImageServer:
    """LeRobot's ZMQ image-server protocol on a free port: JSON {timestamps, images: {name:
    base64 jpeg}} on PUB, a 24x32 frame every 10 ms whose grey level counts the frames sent."""

    def __init__(self, name: str = "front") -> None:
        self.context = zmq.Context()
        self.socket = self.context.socket(zmq.PUB)
        self.port = self.socket.bind_to_random_port("tcp://127.0.0.1")
        self.name = name
        self.sent = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            image = np.full((24, 32, 3), self.sent % 250, np.uint8)
            ok, buf = cv2.imencode(".jpg", image)
            assert ok
            message = {
                "timestamps": {self.name: time.time()},
                "images": {self.name: base64.b64encode(buf.tobytes()).decode()},
            }
            self.socket.send_string(json.dumps(message))
            self.sent += 1
            time.sleep(0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.socket.close(linger=0)
        self.context.term()


def trace_session_options(trace=None, task: str = "PickupBox", **overrides):
    """``SessionOptions`` of a headless session replaying ``trace`` (None: the task's bundled
    one) on the virtual clock, no browser view and no progress line; ``overrides`` win."""
    from beavr_sim.teleop.session import SessionOptions

    kwargs = {
        "task": task,
        "source": "trace",
        "trace": trace,
        "clock": "virtual",
        "viser": False,
        "headless": True,
        "progress": False,
    }
    return SessionOptions(**{**kwargs, **overrides})


class FrameSink:
    """A dataset writer's interface that keeps the frames it is given (the recorder's tests
    judge the frames with LeRobot's own validation; its dataset I/O is tested elsewhere)."""

    root = "unused"
    num_episodes = 0

    def __init__(self):
        self.frames: list[dict] = []

    def add_frame(self, row: dict, task: str) -> None:
        self.frames.append({**row, "task": task})

    def discard_episode(self) -> None:
        pass
