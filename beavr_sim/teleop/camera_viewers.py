"""The session's camera panels streamed to its viewers (``--camera-stream-hz``).

:func:`start_camera_stream` builds one :class:`~beavr_sim.cameras.stream.CameraStream` for the
session's :class:`~beavr_sim.cameras.real.RealCameras` (if any), the twin's renders of them
(a :class:`~beavr_sim.teleop.twin_camera_feed.TwinCameraFeed`, if given: the panels' ``twin``,
``both`` and ``overlay`` views, and twin-only panels in a session without real cameras) and
the viewers it has: the browser view's camera panel, the WebXR page, the Quest app's camera
panel (every panel in one image, in place of the twin's images). A depth camera's depth map is
a panel of its own (``NAME_depth``, coloured). The stream reads the cameras'
newest frames itself (``RealCameras.peek``, counting nothing) and renders, composes and sends
on its own thread at the rate asked, dropping what its viewers cannot take; the control thread
only copies the twin's pose for it. Nothing is started when the rate is 0 (off).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from beavr_sim.cameras.stream import CameraStream, StreamConfig


@dataclass(frozen=True)
class CameraViewers:
    """Where a session's camera panels can be shown: ``view`` (a ``TwinView``), ``webxr`` (a
    ``WebXRServer``), ``quest`` (a ``HeadsetImagePublisher`` the stream may use alone); and
    ``twin`` (a ``TwinCameraFeed``, already a tick listener of the loop) with ``twin_panels``:
    the twin-only panels' names when there is no real camera."""

    view: object | None = None
    webxr: object | None = None
    quest: object | None = None
    twin: object | None = None
    twin_panels: Sequence[str] = ()


def start_camera_stream(real, config: StreamConfig, viewers: CameraViewers) -> CameraStream | None:
    """A running stream of ``real``'s cameras (and the twin's renders) to ``viewers`` (None when
    off or unseen); the caller closes it before the cameras."""
    twin = viewers.twin
    if config.rate_hz <= 0 or (real is None and twin is None):
        return None
    from beavr_sim.cameras.headset_panels import (  # local: heavy (OpenCV, Pillow)
        QuestCameraSink,
        WebXRCameraSink,
    )
    from beavr_sim.cameras.real import DEPTH_SUFFIX  # local: heavy (LeRobot)
    from beavr_sim.cameras.stream import CameraStream  # local: heavy (OpenCV, ~170 ms)

    # every image a grab returns: each camera's, then each depth camera's NAME_depth
    names = tuple(real.names) if real is not None else ()
    shapes = {name: real.frame_shape(name) for name in names}
    depth = {n + DEPTH_SUFFIX: n for n in real.depth_cameras} if real is not None else {}
    if not names and twin is not None:
        shapes = {name: twin.panel_shape(name) for name in viewers.twin_panels}
    sinks = []
    panel = None
    if viewers.view is not None:
        panel = viewers.view.add_camera_panel(shapes)
        sinks.append(panel)
    if viewers.webxr is not None:
        sinks.append(WebXRCameraSink(viewers.webxr))
    if viewers.quest is not None and shapes:  # every panel, in one image
        sinks.append(QuestCameraSink(viewers.quest, tuple(shapes)))
    if not sinks or not shapes:
        return None
    source = real.peek if real is not None else None  # twin-only: the stream's own clock
    stream = CameraStream(config, sinks, shapes, source=source, twin=twin, real=names, depth=depth)
    if panel is not None:
        panel.attach(stream)
    return stream
