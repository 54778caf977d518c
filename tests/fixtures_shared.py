"""Test helpers several test files share (imported as ``from fixtures_shared import ...``:
``tests/`` is on the path, as for ``waiting.py``)."""

from __future__ import annotations

import base64
import contextlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import zmq

#: The wheel whose MuJoCo models (Franka Panda, Shadow hand) the robot-file tests read.
ROBOTICS_PACKAGE, ROBOTICS_VERSION = "gymnasium_robotics", "1.4.2"


def unpacked_robotics_wheel() -> Path | None:
    """A folder holding gymnasium-robotics (to put on ``sys.path``), or None when it is
    installed. Downloaded once with pip into ``~/.cache/beavr_sim/wheels`` and unpacked there;
    the calling test skips, saying why, when that fails (no network). Safe when several test
    processes (pytest-xdist workers) call it at once: each downloads and unpacks into a
    private folder and renames the result into place."""
    if importlib.util.find_spec(ROBOTICS_PACKAGE) is not None:
        return None
    cache = Path.home() / ".cache" / "beavr_sim" / "wheels"
    cache.mkdir(parents=True, exist_ok=True)
    folder = cache / f"{ROBOTICS_PACKAGE}-{ROBOTICS_VERSION}"
    if (folder / ROBOTICS_PACKAGE / "__init__.py").is_file():
        return folder
    wheel = cache / f"{ROBOTICS_PACKAGE}-{ROBOTICS_VERSION}-py3-none-any.whl"
    if not wheel.is_file():
        private = Path(tempfile.mkdtemp(dir=cache, prefix="download."))
        command = [sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "--retries",
                   "1", f"gymnasium-robotics=={ROBOTICS_VERSION}", "-d", str(private)]  # fmt: skip
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=300)
            if done.returncode != 0 or not (private / wheel.name).is_file():
                last = (done.stderr.strip().splitlines() or ["no output"])[-1]
                pytest.skip(
                    f"gymnasium-robotics {ROBOTICS_VERSION} could not be downloaded: {last}"
                )
            os.replace(private / wheel.name, wheel)
        except (OSError, subprocess.TimeoutExpired) as e:
            pytest.skip(f"gymnasium-robotics {ROBOTICS_VERSION} could not be downloaded: {e}")
        finally:
            shutil.rmtree(private, ignore_errors=True)
    partial = Path(tempfile.mkdtemp(dir=cache, prefix=folder.name + "."))
    with zipfile.ZipFile(wheel) as z:
        z.extractall(partial)
    try:
        partial.rename(folder)
    except OSError:  # another process unpacked it meanwhile
        shutil.rmtree(partial)
    return folder


@contextlib.contextmanager
def robotics_wheel_on_path() -> Iterator[None]:
    """gymnasium-robotics importable (not imported) inside the block."""
    folder = unpacked_robotics_wheel()
    with pytest.MonkeyPatch.context() as mp:
        if folder is not None:
            mp.syspath_prepend(str(folder))
        yield


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
