"""Camera-stream sinks for the headset: the Quest app's camera-panel PUB stream and the WebXR
page's camera panel.

Both are :data:`~beavr_sim.cameras.stream.Sink` callables run on the camera stream's worker
thread (never the control thread). The Quest app shows one image stream: :class:`QuestCameraSink`
forwards one named camera's panels to a ``HeadsetImagePublisher`` (which paces and encodes; its
short send queue drops what a slow headset cannot take). :class:`WebXRCameraSink` publishes each
panel as a ``camera`` message (base64 JPEG, state, age) that the page shows as an image with its
age, or NO SIGNAL; the server skips pages whose send buffer is full.
"""

from __future__ import annotations

import base64

from beavr_sim.cameras.stream import StreamFrame
from beavr_sim.headset.quest_io import encode_jpeg
from beavr_sim.headset.webxr_protocol import PROTOCOL_VERSION


class QuestCameraSink:
    """Forwards camera ``name``'s panels to ``publisher`` (a ``HeadsetImagePublisher``)."""

    def __init__(self, publisher, name: str) -> None:
        self.publisher = publisher
        self.name = name

    def __call__(self, frame: StreamFrame) -> None:
        if frame.name == self.name:
            self.publisher.publish(frame.image)


def camera_message(frame: StreamFrame, jpeg_quality: int = 70) -> dict:
    """The WebXR ``camera`` message of one panel."""
    return {
        "v": PROTOCOL_VERSION,
        "type": "camera",
        "name": frame.name,
        "state": frame.state,
        "age_ms": None if frame.age_s is None else round(frame.age_s * 1e3, 1),
        "seq": frame.seq,
        "label": frame.label,
        "jpeg": base64.b64encode(encode_jpeg(frame.image, jpeg_quality)).decode(),
    }


class WebXRCameraSink:
    """Publishes each panel to the WebXR page (``server``: a ``WebXRServer``)."""

    def __init__(self, server, jpeg_quality: int = 70) -> None:
        self.server = server
        self.jpeg_quality = jpeg_quality

    def __call__(self, frame: StreamFrame) -> None:
        self.server.publish(f"camera:{frame.name}", camera_message(frame, self.jpeg_quality))
