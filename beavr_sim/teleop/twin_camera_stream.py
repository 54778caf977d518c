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
from typing import TYPE_CHECKING

from beavr_sim.teleop.camera_viewers import (
    CameraViewers,
    panel_names,
    quest_panels,
    start_camera_stream,
)
from beavr_sim.teleop.twin_camera_feed import twin_feed, twin_panel_names
from beavr_sim.wire.messages import CameraPanelMsg

if TYPE_CHECKING:
    from beavr_sim.cameras.stream import StreamConfig

#: The state stream's topic of the WebXR page's camera panels.
PANEL_TOPIC = b"camera"


@dataclass(frozen=True)
class TwinCameraStream:
    """The twin process's camera stream: ``stream``, the session's ``StreamConfig`` (rate,
    view, the Quest's panels: the one config of both layouts), the twin-only panels' names
    (the cameras ``--camera-poses`` places; none: the headset's camera) and the twin cameras
    whose recorded depth is a twin-only panel too (``depth``), and whether the session has the
    Quest app (``quest``), whose camera panel then shows the streamed panels (one image, a
    grid), composed in the view chosen, in place of the twin's headset images: with real
    cameras, or when ``stream.quest_panels`` chose panels (else those images stay)."""

    stream: StreamConfig
    placed: tuple[str, ...] = ()
    depth: tuple[str, ...] = ()
    quest: bool = False
    #: The WebXR page's panels, sent to the operator process that hosts its server.
    page: bool = False
    #: Without ``--record`` the stream's own real cameras (``--camera`` specs, the mirrored
    #: rig file's tables); recording, the recorder's are streamed.
    real_cameras: tuple[str, ...] = ()
    rig_file: str | None = None

    def __post_init__(self) -> None:
        if not self.stream.rate_hz > 0:
            raise ValueError(
                f"the twin's camera stream rate must be > 0, got {self.stream.rate_hz}"
            )

    @property
    def rate_hz(self) -> float:
        return self.stream.rate_hz

    def quest_shows_panels(self, real) -> bool:
        """The Quest app's camera panel shows the streamed panels (``real``: the connected
        ``RealCameras`` or None), in place of the twin's headset images."""
        return self.quest and (real is not None or self.stream.quest_panels is not None)


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


def check_quest_panels(config: TwinCameraStream, env, real) -> tuple[str, ...]:
    """The panels the Quest app will show of this stream (``real``: the connected
    ``RealCameras`` or None); a ``--quest-cameras`` name that is no panel is one line
    (``UnknownNameError``), raised at the twin process's start, before anything streams."""
    cameras = (real.cameras, real.depth_cameras) if real is not None else ((), ())
    panels = panel_names(*cameras, twin_panel_names(env, config.placed), config.depth)
    return quest_panels(config.stream.quest_panels, panels)


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
        # the Quest app's panel shows the streamed panels (in the view chosen) in place of the
        # twin's headset images (which stay alone without real cameras, unless chosen)
        quest=quest if config.quest_shows_panels(real) else None,
        twin=feed,
        twin_panels=panels,
        twin_depth=config.depth,
    )
    stream = start_camera_stream(real, config.stream, viewers)

    return stream.close if stream is not None else lambda: None  # (it closes the feed)
