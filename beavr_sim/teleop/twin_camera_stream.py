"""``--camera-stream-hz`` under ``--multiprocess``: the camera panels streamed from the twin process.

The twin process holds what the panels show (the real cameras, read next to the recorder, and
the twin's scene) and two of their viewers (the browser view, the Quest app's image socket), so
the stream runs there: :func:`attach_camera_stream` builds the same
:func:`~beavr_sim.teleop.camera_viewers.start_camera_stream` as one process, its twin renders
fed by a :class:`~beavr_sim.teleop.twin_camera_feed.TwinCameraFeed` on the twin stage's
``after_step`` hook (the step only copies the pose, at the stream's rate). The WebXR page's
server is the operator process's: its panels are encoded on the stream's thread into
:class:`PagePanels` (the newest per camera), which the twin's loop sends after its state
(:class:`~beavr_sim.wire.messages.CameraPanelMsg` on the state stream, topic ``camera``) and
the operator hands to its page server.

Contract: :class:`TwinCameraStream` is frozen (passed whole to the spawned twin); the returned
closer stops the stream before the cameras it reads and the viewers it sends to are closed.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from dataclasses import dataclass

from beavr_sim.teleop.camera_viewers import CameraViewers, start_camera_stream
from beavr_sim.teleop.twin_camera_feed import twin_feed
from beavr_sim.wire.messages import CameraPanelMsg

#: The state stream's topic of the WebXR page's camera panels.
PANEL_TOPIC = b"camera"


@dataclass(frozen=True)
class TwinCameraStream:
    """The twin process's camera stream: ``rate_hz`` panels per second, the ``view`` asked
    (``auto`` or one of ``beavr_sim.cameras.stream.VIEWS``), the twin-only panels' names (the
    cameras ``--camera-poses`` places; none: the headset's camera), and whether the Quest
    app's camera panel shows every real camera's panel (one image, a grid), composed in the
    view chosen (in place of the twin's headset images, which stay when there is no real
    camera)."""

    rate_hz: float
    view: str = "auto"
    placed: tuple[str, ...] = ()
    quest: bool = False
    #: The WebXR page's panels, sent to the operator process that hosts its server.
    page: bool = False
    #: Without ``--record`` the stream's own real cameras (``--camera`` specs, the mirrored
    #: rig file's tables); recording, the recorder's are streamed.
    real_cameras: tuple[str, ...] = ()
    rig_file: str | None = None

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ValueError(f"the twin's camera stream rate must be > 0, got {self.rate_hz}")

    def stream_config(self):
        """The stream's ``StreamConfig``."""
        from beavr_sim.cameras.stream import StreamConfig  # local: heavy (OpenCV, ~170 ms)

        return StreamConfig(rate_hz=self.rate_hz, view=self.view)


class PagePanels:
    """The WebXR page's panels on their way to the operator process: the stream's WebXR sink
    publishes here (its thread; encoded there), the twin's loop :meth:`take` s the newest of
    each camera (older ones are replaced, never queued)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._newest: dict[str, CameraPanelMsg] = {}

    def publish(self, kind: str, message: dict) -> None:
        panel = CameraPanelMsg(kind=kind, message=json.dumps(message))
        with self._lock:
            self._newest[kind] = panel

    def take(self) -> list[CameraPanelMsg]:
        with self._lock:
            newest, self._newest = self._newest, {}
        return list(newest.values())


def attach_camera_stream(
    config: TwinCameraStream, env, stage, real, view=None, quest=None, page=None
) -> Callable[[], None]:
    """Stream ``real``'s cameras (a connected ``RealCameras`` or None) and the twin's renders
    of ``env`` to ``view`` (a ``TwinView``), ``page`` (:class:`PagePanels`) and ``quest`` (a ``HeadsetImagePublisher``, used
    when ``config.quest``); the feed follows ``stage``'s steps. Returns the stream's closer."""
    feed, panels = twin_feed(env, config.rate_hz, config.placed)
    stage.after_step.append(feed)
    viewers = CameraViewers(
        view=view,
        webxr=page,
        # the Quest app's panel shows every real camera's panel (in the view chosen) in place
        # of the twin's headset images; without a real camera those images stay alone
        quest=quest if config.quest and real is not None else None,
        twin=feed,
        twin_panels=panels,
    )
    stream = start_camera_stream(real, config.stream_config(), viewers)

    return stream.close if stream is not None else lambda: None  # (it closes the feed)
