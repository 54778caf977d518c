"""Camera-stream sinks for the headset: the Quest app's camera-panel PUB stream and the WebXR
page's camera panel.

Both are :data:`~beavr_sim.cameras.stream.Sink` callables run on the camera stream's worker
thread (never the control thread). The Quest app shows one image stream (one JPEG per message,
its panel a texture of the image's size): :class:`QuestCameraSink` composes the panels it is
given (every panel of the stream, or those ``--quest-cameras`` chose) into that one image, a grid of tiles each labelled with its panel's line (one panel: the
panel alone, as composed), at most :data:`QUEST_IMAGE_MAX` pixels, and forwards it to a
``HeadsetImagePublisher`` (which paces and encodes; its short send queue drops what a slow
headset cannot take). :class:`WebXRCameraSink` publishes each panel as a ``camera`` message
(base64 JPEG, state, age, and where the panel stands in the scene) that the page shows as an
image with its age, or NO SIGNAL, in its overlay and as a textured quad in the immersive scene
beyond the table (:func:`panel_placement`, moved from there by the page's own offset); the
server skips pages whose send buffer is full.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Sequence

import cv2
import numpy as np

from beavr_sim.cameras.stream import LIVE, StreamFrame, no_signal_image
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
#: The Quest panel's image at most (height, width) pixels: a grid of several panels is scaled
#: down, aspect kept, to fit (the app's panel starts at 640x360 and takes the image's size).
QUEST_IMAGE_MAX = (960, 1280)


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
    """Forwards the stream's panels (``names``, in the stream's order) to ``publisher`` (a
    ``HeadsetImagePublisher``) as one image: each time the last panel of a round arrives, the
    grid of every panel's newest frame (:func:`quest_grid`; a panel not seen yet reads NO
    SIGNAL)."""

    def __init__(self, publisher, names: Sequence[str]) -> None:
        if not names:
            raise ValueError("the Quest camera panel needs at least one camera panel")
        self.publisher = publisher
        self.names = tuple(names)
        self._newest: dict[str, StreamFrame] = {}

    def __call__(self, frame: StreamFrame) -> None:
        if frame.name not in self.names:
            return
        self._newest[frame.name] = frame
        if frame.name == self.names[-1]:  # a round is complete: one image for the panel
            self.publisher.publish(quest_grid([self._newest.get(n, n) for n in self.names]))


def grid_layout(
    n: int, cell: tuple[int, int], limit: tuple[int, int] = QUEST_IMAGE_MAX
) -> tuple[int, int, float]:
    """(rows, columns, scale) of ``n`` tiles of ``cell`` (height, width) pixels: the layout
    that draws them largest within ``limit`` (ties: more columns), never scaled up."""
    best = (1, n, 0.0)
    for cols in range(n, 0, -1):
        rows = math.ceil(n / cols)
        scale = min(1.0, limit[0] / (rows * cell[0]), limit[1] / (cols * cell[1]))
        if scale > best[2] + 1e-9:
            best = (rows, cols, scale)
    return best


def quest_grid(
    panels: Sequence[StreamFrame | str], limit: tuple[int, int] = QUEST_IMAGE_MAX
) -> np.ndarray:
    """One RGB image of ``panels`` (a name: a panel not seen yet, drawn NO SIGNAL): one panel
    is its image; several are tiles of a grid (:func:`grid_layout`), each image fitted into
    its tile (aspect kept, black bars) under a line naming it (its label), within ``limit``."""
    frames = [p for p in panels if isinstance(p, StreamFrame)]
    if len(panels) == 1 and frames:
        return frames[0].image
    shape = frames[0].image.shape if frames else (480, 640, 3)
    cell = (max(int(f.image.shape[0]) for f in frames) if frames else int(shape[0]),
            max(int(f.image.shape[1]) for f in frames) if frames else int(shape[1]))  # fmt: skip
    rows, cols, scale = grid_layout(len(panels), cell, limit)
    th, tw = max(1, int(cell[0] * scale)), max(1, int(cell[1] * scale))
    image = np.zeros((rows * th, cols * tw, 3), np.uint8)
    for i, panel in enumerate(panels):
        if isinstance(panel, StreamFrame):
            tile, label, live = panel.image, panel.label, panel.state == LIVE
        else:
            tile, label, live = no_signal_image((th, tw, 3), panel), f"{panel}: NO SIGNAL", False
        y, x = (i // cols) * th, (i % cols) * tw
        image[y : y + th, x : x + tw] = _fit_tile(tile, th, tw)
        _label(image[y : y + th, x : x + tw], label, live)
    return image


def _fit_tile(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``image`` scaled into (height, width), aspect kept, centred on black."""
    h, w = int(image.shape[0]), int(image.shape[1])
    scale = min(height / h, width / w)
    fh, fw = max(1, round(h * scale)), max(1, round(w * scale))
    if (fh, fw) != (h, w):
        image = cv2.resize(image, (fw, fh), interpolation=cv2.INTER_AREA)
    tile = np.zeros((height, width, 3), np.uint8)
    y, x = (height - fh) // 2, (width - fw) // 2
    tile[y : y + fh, x : x + fw] = image
    return tile


def _label(tile: np.ndarray, text: str, live: bool) -> None:
    """``text`` on a dark strip along the tile's top (red when not live)."""
    scale = max(0.35, tile.shape[1] / 900.0)
    (_, text_h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    strip = min(tile.shape[0], text_h + base + 6)
    tile[:strip] = (tile[:strip] * 0.3).astype(np.uint8)
    colour = (235, 235, 235) if live else (230, 60, 60)
    cv2.putText(
        tile, text, (4, strip - base - 2), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1,
        cv2.LINE_AA,
    )  # fmt: skip


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
