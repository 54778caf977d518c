"""The session's real cameras streamed to its viewers (``--camera-stream-hz``).

:func:`start_camera_stream` builds one :class:`~beavr_sim.cameras.stream.CameraStream` for the
session's :class:`~beavr_sim.cameras.real.RealCameras` and the viewers it has: the browser
view's camera panel, the WebXR page, the Quest app's camera panel (the first real camera,
in place of the twin's images). The stream reads the cameras' newest frames itself
(``RealCameras.peek``, counting nothing) and composes and sends on its own thread at the rate
asked, dropping what its viewers cannot take; the control thread does nothing for it. Nothing is started when the rate is 0 (off).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from beavr_sim.cameras.stream import CameraStream, StreamConfig


@dataclass(frozen=True)
class CameraViewers:
    """Where a session's real cameras can be shown: ``view`` (a ``TwinView``), ``webxr`` (a
    ``WebXRServer``), ``quest`` (a ``HeadsetImagePublisher`` the stream may use alone)."""

    view: object | None = None
    webxr: object | None = None
    quest: object | None = None


def start_camera_stream(real, config: StreamConfig, viewers: CameraViewers) -> CameraStream | None:
    """A running stream of ``real``'s cameras to ``viewers`` (None when off or unseen);
    the caller closes it before the cameras."""
    if real is None or config.rate_hz <= 0:
        return None
    from beavr_sim.cameras.headset_panels import (  # local: heavy (OpenCV, Pillow)
        QuestCameraSink,
        WebXRCameraSink,
    )
    from beavr_sim.cameras.stream import CameraStream  # local: heavy (OpenCV, ~170 ms)

    shapes = {name: real.frame_shape(name) for name in real.names}
    sinks = []
    panel = None
    if viewers.view is not None:
        panel = viewers.view.add_camera_panel(shapes)
        sinks.append(panel)
    if viewers.webxr is not None:
        sinks.append(WebXRCameraSink(viewers.webxr))
    if viewers.quest is not None and real.names:
        sinks.append(QuestCameraSink(viewers.quest, real.names[0]))
    if not sinks:
        return None
    stream = CameraStream(config, sinks, shapes, source=real.peek)
    if panel is not None:
        panel.attach(stream)
    return stream
