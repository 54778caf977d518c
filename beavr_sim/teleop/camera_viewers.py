"""The session's camera panels streamed to its viewers (``--camera-stream-hz``).

:func:`start_camera_stream` builds one :class:`~beavr_sim.cameras.stream.CameraStream` for the
session's :class:`~beavr_sim.cameras.real.RealCameras` (if any), the twin's renders of them
(a :class:`~beavr_sim.teleop.twin_camera_feed.TwinCameraFeed`, if given: the panels' ``twin``,
``both`` and ``overlay`` views, and twin-only panels in a session without real cameras) and
the viewers it has: the browser view's camera panel, the WebXR page, the Quest app's camera
panel (every panel, or those ``StreamConfig.quest_panels`` names, in one image, in place of the
twin's images). A depth camera's depth map is a panel of its own (``NAME_depth``, coloured);
so, in a session without real cameras, is the twin's depth of each twin camera whose depth is
recorded (``--cameras NAME:depth``). The stream reads the cameras'
newest frames itself (``RealCameras.peek``, counting nothing) and renders, composes and sends
on its own thread at the rate asked, dropping what its viewers cannot take; the control thread
only copies the twin's pose for it. Nothing is started when the rate is 0 (off).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from beavr_sim.naming import check_name
from beavr_sim.teleop.twin_camera_feed import DEPTH_SUFFIX

if TYPE_CHECKING:
    from beavr_sim.cameras.stream import CameraStream, StreamConfig


@dataclass(frozen=True)
class CameraViewers:
    """Where a session's camera panels can be shown: ``view`` (a ``TwinView``), ``webxr`` (a
    ``WebXRServer``), ``quest`` (a ``HeadsetImagePublisher`` the stream may use alone); and
    ``twin`` (a ``TwinCameraFeed``, already a tick listener of the loop) with ``twin_panels``:
    the twin-only panels' names when there is no real camera, and ``twin_depth``: the twin
    cameras whose depth is a twin-only panel too (``NAME_depth``: the recorded twin depth)."""

    view: object | None = None
    webxr: object | None = None
    quest: object | None = None
    twin: object | None = None
    twin_panels: Sequence[str] = ()
    twin_depth: Sequence[str] = ()


def panel_names(
    real: Sequence[str],
    real_depth: Sequence[str] = (),
    twin_panels: Sequence[str] = (),
    twin_depth: Sequence[str] = (),
) -> tuple[str, ...]:
    """A stream's panels in order: each real camera, then ``NAME_depth`` of each real depth
    camera; without a real camera, the twin's panels, then ``NAME_depth`` of each twin camera
    in ``twin_depth``."""
    if real:
        return (*real, *(n + DEPTH_SUFFIX for n in real_depth))
    return tuple(dict.fromkeys((*twin_panels, *(n + DEPTH_SUFFIX for n in twin_depth))))


def parse_quest_cameras(text: str | None) -> tuple[str, ...] | None:
    """``--quest-cameras NAME[,NAME...]`` -> the names (None: not given, every panel)."""
    if text is None:
        return None
    names = tuple(n.strip() for n in text.split(","))
    if not all(names):
        raise ValueError(f"--quest-cameras takes NAME[,NAME...], got {text!r}")
    return names


def quest_panels(chosen: Sequence[str] | None, panels: Sequence[str]) -> tuple[str, ...]:
    """The panels the Quest app shows, in the stream's order: ``chosen`` (``--quest-cameras``;
    None: every panel); a name that is no panel is one line listing the panels there are."""
    if chosen is None:
        return tuple(panels)
    for name in chosen:
        check_name("Quest camera panel", name, panels, "(--quest-cameras)")
    return tuple(n for n in panels if n in chosen)


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
    from beavr_sim.cameras.stream import CameraStream  # local: heavy (OpenCV, ~170 ms)

    # every image a grab returns: each camera's, then each depth camera's NAME_depth; without
    # real cameras the twin's panels, then its recorded depth cameras' NAME_depth
    names = tuple(real.cameras) if real is not None else ()
    real_depth = tuple(real.depth_cameras) if real is not None else ()
    twin_depth = tuple(viewers.twin_depth) if twin is not None else ()
    panels = panel_names(names, real_depth, viewers.twin_panels if twin else (), twin_depth)
    depth = {n + DEPTH_SUFFIX: n for n in (real_depth if names else twin_depth)}
    if names:
        names = panels
        shapes = {name: real.frame_shape(name) for name in panels}
    else:
        shapes = {name: _twin_shape(twin, depth.get(name), name) for name in panels}
    on_quest = quest_panels(config.quest_panels, tuple(shapes))  # a bad name fails here
    sinks = []
    panel = None
    if viewers.view is not None:
        panel = viewers.view.add_camera_panel(shapes)
        sinks.append(panel)
    if viewers.webxr is not None:
        sinks.append(WebXRCameraSink(viewers.webxr))
    if viewers.quest is not None and on_quest:  # the chosen panels (all), in one image
        sinks.append(QuestCameraSink(viewers.quest, on_quest))
    if not sinks or not shapes:
        return None
    source = real.peek if real is not None else None  # twin-only: the stream's own clock
    stream = CameraStream(config, sinks, shapes, source=source, twin=twin, real=names, depth=depth)
    if panel is not None:
        panel.attach(stream)
    return stream


def _twin_shape(twin, depth_of: str | None, panel: str) -> tuple[int, int, int]:
    """A twin-only panel's shape: its camera's (one channel for ``depth_of``'s depth)."""
    if depth_of is None:
        return twin.panel_shape(panel)
    height, width, _ = twin.panel_shape(depth_of)
    return (height, width, 1)
