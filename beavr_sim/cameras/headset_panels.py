"""Camera-stream sinks for the headset: the Quest app's camera-panel PUB stream and the WebXR
page's camera panel.

Both are :data:`~beavr_sim.cameras.stream.Sink` callables run on the camera stream's worker
thread (never the control thread). The Quest app shows one image stream: :class:`QuestCameraSink`
forwards one named camera's panels to a ``HeadsetImagePublisher`` (which paces and encodes; its
short send queue drops what a slow headset cannot take). :class:`WebXRCameraSink` publishes each
panel as a ``camera`` message (base64 JPEG, state, age, and where the panel stands in the
scene) that the page shows as an image with its age, or NO SIGNAL, in its overlay and as a
textured quad in the immersive scene beyond the table (:func:`panel_placement`); the server
skips pages whose send buffer is full.
"""

from __future__ import annotations

import base64

from beavr_sim.cameras.stream import StreamFrame
from beavr_sim.headset.quest_io import encode_jpeg
from beavr_sim.headset.webxr_protocol import PROTOCOL_VERSION
from beavr_sim.workcell import TABLE_TOP_Z, TABLE_X

#: The in-scene panels: PANEL_WIDTH_M wide (the height follows the image), the first centred
#: on the robot's axis just beyond the table's far edge, PANEL_RAISE_M over the table top,
#: facing the operator (world -x); the next ones to the operator's right (world -y).
PANEL_WIDTH_M = 0.5
PANEL_GAP_M = 0.05
PANEL_RAISE_M = 0.4
PANEL_BEYOND_TABLE_M = 0.05


def panel_placement(index: int) -> dict:
    """Where the ``index``-th camera's quad stands: its centre in the world frame (m, z up)
    and its width; it faces the operator (world -x), its image's right along world -y."""
    return {
        "center": [
            TABLE_X[1] + PANEL_BEYOND_TABLE_M,
            -index * (PANEL_WIDTH_M + PANEL_GAP_M),
            TABLE_TOP_Z + PANEL_RAISE_M,
        ],
        "width_m": PANEL_WIDTH_M,
    }


class QuestCameraSink:
    """Forwards camera ``name``'s panels to ``publisher`` (a ``HeadsetImagePublisher``)."""

    def __init__(self, publisher, name: str) -> None:
        self.publisher = publisher
        self.name = name

    def __call__(self, frame: StreamFrame) -> None:
        if frame.name == self.name:
            self.publisher.publish(frame.image)


def camera_message(frame: StreamFrame, jpeg_quality: int = 70, index: int = 0) -> dict:
    """The WebXR ``camera`` message of one panel, the ``index``-th in the scene."""
    return {
        "v": PROTOCOL_VERSION,
        "type": "camera",
        "name": frame.name,
        "state": frame.state,
        "age_ms": None if frame.age_s is None else round(frame.age_s * 1e3, 1),
        "seq": frame.seq,
        "t": round(frame.t_s, 4),
        "label": frame.label,
        "width": int(frame.image.shape[1]),
        "height": int(frame.image.shape[0]),
        "panel": panel_placement(index),
        "jpeg": base64.b64encode(encode_jpeg(frame.image, jpeg_quality)).decode(),
    }


class WebXRCameraSink:
    """Publishes each panel to the WebXR page (``server``: a ``WebXRServer``)."""

    def __init__(self, server, jpeg_quality: int = 70) -> None:
        self.server = server
        self.jpeg_quality = jpeg_quality
        self.order: dict[str, int] = {}  # each camera's place in the scene, first seen first

    def __call__(self, frame: StreamFrame) -> None:
        index = self.order.setdefault(frame.name, len(self.order))
        message = camera_message(frame, self.jpeg_quality, index)
        self.server.publish(f"camera:{frame.name}", message)
