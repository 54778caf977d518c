"""CameraStream: the live real cameras and the twin's renders of them streamed to viewers off the
control thread, at a bounded rate.

Contract: the control thread's only call, if any, is :meth:`CameraStream.offer`; it stores a
reference to a :class:`~beavr_sim.cameras.real.Grab` (and the twin's renders) in a one-slot
mailbox and returns (never blocks, never raises, never copies). Given a ``source`` (a
``RealCameras.peek``), the stream reads the cameras' newest frames itself, on its own thread,
whenever nothing was offered. Given a ``twin`` (a :class:`TwinSource`), the stream's own thread
renders the twin's view of each panel when the view shows it (``twin``, ``both``,
``overlay``), and always for twin-only panels (names not in ``real``: a session with no real
camera of that name). A worker thread wakes at most ``rate_hz`` times per second, takes the
newest grab (older ones are dropped and counted, never queued), composes each panel for the
chosen view (``real``, ``twin``, ``both`` side by side, or ``overlay``: the twin's render
blended over the real frame) and hands a :class:`StreamFrame` to every sink (the viser panel,
the Quest image PUB socket, the WebXR page). A slow sink slows only the worker. With nothing
offered and no source for ``dead_after_s``, the panels turn to "no signal" (a viewer is never
left showing a last frame as live). A camera that is dead, or whose newest frame is older than
``dead_after_s`` when shown, is drawn as "no signal" (never its last image shown as live), and
so is a twin render older than that (the twin stopped ticking); every live frame carries its
capture age.

Depth panels (``depth``: a depth camera's ``NAME_depth`` feature, HxWx1 uint16 millimetres, or
the twin's depth render, HxWx1 float32 metres) are drawn in one fixed colour map,
:func:`colour_depth` (:data:`DEPTH_RANGE_M`, invalid depth black), and then composed in the
chosen view like colour panels: ``both`` is the real depth beside the twin's depth of the
same camera, ``overlay`` one blended over the other.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

log = logging.getLogger(__name__)

#: What a camera panel shows: the real frame, the twin's render, both side by side, or the
#: twin's render blended over the real frame.
VIEWS = ("real", "twin", "both", "overlay")
#: ``--camera-view auto``: ``both`` where a real camera has a twin camera of its name (one the
#: scene has, or ``--camera-poses`` places at its pose), else ``real``; twin-only panels: ``twin``.
AUTO = "auto"
#: Streamed frames per second by default: low, the stream is for a person watching.
DEFAULT_RATE_HZ = 5.0
NO_SIGNAL = "no signal"
LIVE = "live"
#: Depth drawn in colour between these distances (m): nearer is the near colour (blue), farther
#: the far colour (red); 0 (a depth camera's "no reading") and non-finite depth are black.
DEPTH_RANGE_M = (0.2, 2.0)
#: The part of OpenCV's TURBO colour map used (blue .. green .. yellow .. red): its darkest
#: ends are left out so that no valid depth reads as black.
_DEPTH_LUT_SPAN = (16, 240)


@dataclass(frozen=True)
class StreamConfig:
    """``rate_hz``: panels per second at most (``0``: the stream is off); ``view``: one of
    :data:`VIEWS`; ``blend``: the twin's weight in ``overlay`` (0..1); ``dead_after_s``: a
    frame older than this when shown is "no signal"; ``quest_panels``: the panels the Quest
    app's camera panel shows (``--quest-cameras``; None: every panel), checked against the
    session's panels when the stream starts."""

    rate_hz: float = DEFAULT_RATE_HZ
    view: str = "real"
    blend: float = 0.5
    dead_after_s: float = 1.0
    quest_panels: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.view != AUTO:
            check_view(self.view)
        if not (0.0 <= self.rate_hz <= 120.0):
            raise ValueError(f"camera stream rate_hz must be in 0..120, got {self.rate_hz}")
        check_blend(self.blend)
        if self.dead_after_s <= 0:
            raise ValueError(f"dead_after_s must be > 0, got {self.dead_after_s}")
        if self.quest_panels is not None:
            panels = tuple(self.quest_panels)
            if not panels or not all(isinstance(n, str) and n for n in panels):
                raise ValueError(
                    f"--quest-cameras takes panel names, NAME[,NAME...], got {self.quest_panels!r}"
                )
            object.__setattr__(self, "quest_panels", tuple(dict.fromkeys(panels)))


def check_view(view: str) -> str:
    if view not in VIEWS:
        raise ValueError(f"unknown camera view {view!r}; choose one of {', '.join(VIEWS)}")
    return view


def check_blend(blend: float) -> float:
    if not (0.0 <= float(blend) <= 1.0):
        raise ValueError(f"blend must be in 0..1, got {blend}")
    return float(blend)


@dataclass(frozen=True)
class StreamFrame:
    """One camera's panel as streamed: ``image`` (HxWx3 uint8 RGB), ``state`` (``"live"`` or
    ``"no signal"``), ``age_s`` (capture age when composed; None without a signal)."""

    name: str
    image: np.ndarray
    state: str
    age_s: float | None
    seq: int
    #: What else the panel shows (e.g. ``twin front``, ``twin NO SIGNAL``), after the label.
    note: str = ""
    #: When it was composed, on the stream's clock (s; ``time.perf_counter`` by default).
    t_s: float = 0.0

    @property
    def label(self) -> str:
        if self.state != LIVE or self.age_s is None:
            text = f"{self.name}: NO SIGNAL"
        else:
            text = f"{self.name}: live, age {self.age_s * 1e3:.0f} ms"
        return f"{text} ({self.note})" if self.note else text


Sink = Callable[[StreamFrame], None]


class TwinSource(Protocol):
    """The twin's renders for the panels, called on the stream's worker thread only."""

    def render(
        self, shapes: Mapping[str, tuple[int, int, int]]
    ) -> tuple[Mapping[str, np.ndarray], float | None]:
        """Each panel's twin render at (about) its shape (a one-channel shape: the depth of a
        depth panel ``NAME_depth``'s camera, HxWx1 metres), and the twin state's age in
        seconds ({}, None before the twin's first tick)."""
        ...

    def camera_for(self, panel: str) -> str:
        """The twin camera drawn for ``panel``."""
        ...

    def close(self) -> None: ...


class _Silent:
    """A grab in which every camera is dead (what is shown when nothing arrives)."""

    def __init__(self, names: tuple[str, ...]) -> None:
        self.dead = names
        self.frames: dict[str, np.ndarray] = {}
        self.ages_s: dict[str, float] = {}


def no_signal_image(shape: tuple[int, int, int], name: str) -> np.ndarray:
    """A dark grey panel reading NO SIGNAL and the camera's name (never an old image)."""
    h, w = int(shape[0]), int(shape[1])
    image = np.full((h, w, 3), 40, np.uint8)
    scale = max(0.4, w / 640.0)
    for text, y in (("NO SIGNAL", 0.5), (name, 0.5 + 0.12)):
        cv2.putText(
            image, text, (int(0.08 * w), int(y * h)), cv2.FONT_HERSHEY_SIMPLEX, scale,
            (230, 60, 60), max(1, int(2 * scale)), cv2.LINE_AA,
        )  # fmt: skip
    return image


def _depth_lut() -> np.ndarray:
    ramp = np.linspace(*_DEPTH_LUT_SPAN, 256).round().astype(np.uint8).reshape(-1, 1)
    return cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()  # BGR -> RGB


_DEPTH_LUT = _depth_lut()


def colour_depth(depth: np.ndarray) -> np.ndarray:
    """An HxWx3 uint8 RGB image of a depth map: HxW or HxWx1, integer millimetres (a RealSense's
    ``NAME_depth``) or float metres (the twin's), coloured by distance over
    :data:`DEPTH_RANGE_M` (clamped at both ends), 0 and non-finite depth black."""
    depth = np.asarray(depth)
    if depth.ndim == 3:
        depth = depth[..., 0]
    metres = depth.astype(np.float32)
    if np.issubdtype(depth.dtype, np.integer):
        metres *= 1e-3
    near, far = DEPTH_RANGE_M
    valid = np.isfinite(metres) & (metres > 0)
    scaled = (np.clip(np.where(valid, metres, near), near, far) - near) * (255.0 / (far - near))
    image = _DEPTH_LUT[scaled.round().astype(np.uint8)]
    image[~valid] = 0
    return image


def as_panel_image(image: np.ndarray | None) -> np.ndarray | None:
    """A frame as a panel shows it: HxWx3 uint8 as is, a one-channel depth map coloured."""
    if image is None or (image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8):
        return image
    return colour_depth(image)


def compose(
    real: np.ndarray | None, twin: np.ndarray | None, view: str, blend: float
) -> np.ndarray | None:
    """The panel for ``view`` from a real frame and the twin's render (either may be None:
    the view falls back to what there is). The twin's render is resized to the real frame."""
    if real is None:
        return None if twin is None else twin
    if twin is None or view == "real":
        return real
    if twin.shape[:2] != real.shape[:2]:
        twin = cv2.resize(twin, (real.shape[1], real.shape[0]), interpolation=cv2.INTER_AREA)
    if view == "twin":
        return twin
    if view == "both":
        return np.concatenate([real, twin], axis=1)
    return cv2.addWeighted(twin, blend, real, 1.0 - blend, 0.0)


class CameraStream:
    """Streams the newest grab to ``sinks`` from its own thread; :meth:`close` when done.

    ``shapes``: every panel's shape by name; ``real``: the panels that are real cameras
    (default: all); ``depth``: the depth panels (``NAME_depth``, shape HxWx1) by the camera
    whose capture they are (its age and signal are theirs); ``twin``: the twin's renders
    (:class:`TwinSource`), closed on the worker thread when the stream ends."""

    def __init__(
        self,
        config: StreamConfig,
        sinks: Sequence[Sink],
        shapes: Mapping[str, tuple[int, int, int]],
        *,
        source: Callable[[], object] | None = None,
        twin: TwinSource | None = None,
        real: Sequence[str] | None = None,
        depth: Mapping[str, str] | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.config = config
        self.sinks = list(sinks)
        self.shapes = dict(shapes)
        self.real = tuple(self.shapes if real is None else real)
        self.depth = dict(depth or {})
        self.twin = twin
        self.view = config.view if config.view != AUTO else self._auto_view()
        self.blend = config.blend
        self.source = source
        self._clock = clock
        self._twin: Mapping[str, np.ndarray] | None = None
        self._lock = threading.Lock()
        self._slot: tuple[object, Mapping[str, np.ndarray] | None, float] | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        #: Grabs offered, dropped unseen (a newer one replaced them), and panels sent.
        self.offered = 0
        self.dropped = 0
        self.sent = 0
        self.no_signal = 0
        self.sink_errors = 0
        #: Twin renders drawn, and failed (the panel then shows no twin).
        self.twin_renders = 0
        self.twin_errors = 0
        self._seq = 0
        self._thread: threading.Thread | None = None
        if config.rate_hz > 0 and self.sinks:
            self._thread = threading.Thread(target=self._run, name="camera-stream", daemon=True)
            self._thread.start()
        elif twin is not None:
            twin.close()

    def _auto_view(self) -> str:
        if self.twin is not None and any(self.twin.camera_for(n) == n for n in self.real):
            return "both"
        return "real"

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def set_view(self, view: str) -> None:
        self.view = check_view(view)

    def set_blend(self, blend: float) -> None:
        self.blend = check_blend(blend)

    def offer(self, grab, twin: Mapping[str, np.ndarray] | None = None) -> None:
        """The newest grab (and the twin's renders by camera name); control thread, O(1)."""
        if self._thread is None:
            return
        with self._lock:
            if self._slot is not None:
                self.dropped += 1
            self._slot = (grab, twin, self._clock())
            if twin is not None:
                self._twin = twin
            self.offered += 1
        self._wake.set()

    def _take(self):
        with self._lock:
            slot, self._slot = self._slot, None
            self._wake.clear()
        return slot

    def _run(self) -> None:
        try:
            self._loop()
        finally:
            if self.twin is not None:  # its render contexts live on this thread
                try:
                    self.twin.close()
                except Exception as exc:
                    log.warning("camera stream: closing the twin's renders failed: %r", exc)

    def _loop(self) -> None:
        period = 1.0 / self.config.rate_hz
        next_at = last_at = self._clock()
        silent = _Silent(self.real)
        while not self._stop.is_set():
            if self.source is None:
                self._wake.wait(timeout=min(period, 0.25))
            wait = next_at - self._clock()
            if wait > 0 and self._stop.wait(wait):
                return
            now = self._clock()
            slot = self._take()
            if slot is None and self.source is not None:
                try:
                    slot = (self.source(), self._twin, now)
                except Exception as exc:  # a camera closing under us: no signal this time
                    log.debug("camera stream source failed: %r", exc)
                    slot = (silent, None, now)
            if slot is None:
                if now - last_at <= self.config.dead_after_s and self.twin is None:
                    continue
                slot = (silent, None, now)  # nothing offered for a while: no signal
            last_at = now
            next_at = max(next_at + period, now)
            try:
                frames = self.panels(*slot, twin_age_s=None)
            except Exception as exc:  # never let a bad frame end the stream
                log.warning("camera stream: cannot compose a panel: %r", exc)
                continue
            for frame in frames:
                for sink in self.sinks:
                    try:
                        sink(frame)
                    except Exception as exc:  # a viewer going away never ends the stream
                        self.sink_errors += 1
                        log.debug("camera stream sink failed: %r", exc)
                self.sent += 1

    def _view_of(self, name: str) -> str:
        return self.view if name in self.real else "twin"

    def _render_twin(self) -> tuple[Mapping[str, np.ndarray], float | None]:
        """The twin source's renders of the panels whose view shows the twin (worker)."""
        wanted = {
            n: (int(s[0]), int(s[1]), 1 if n in self.depth else 3)
            for n, s in self.shapes.items()
            if self._view_of(n) != "real"
        }
        if self.twin is None or not wanted:
            return {}, None
        try:
            images, age_s = self.twin.render(wanted)
        except Exception as exc:  # a render failing: the twin's part reads NO SIGNAL
            self.twin_errors += 1
            if self.twin_errors == 1 or self.twin_errors % 100 == 0:
                log.warning(
                    "camera stream: the twin's render failed (%d): %r", self.twin_errors, exc
                )
            return {}, None
        self.twin_renders += len(images)
        return {n: as_panel_image(image) for n, image in images.items()}, age_s

    def panels(
        self, grab, twin, offered_at: float, twin_age_s: float | None = None
    ) -> list[StreamFrame]:
        """Each panel for a grab offered at ``offered_at`` (the worker's job). ``twin``: the
        twin's renders by panel name offered with the grab (``twin_age_s`` old; default: as
        old as the grab's offer); with a :class:`TwinSource` the stream renders its own."""
        composed = self._clock()
        waited = max(0.0, composed - offered_at)
        if self.twin is not None:
            twin, twin_age_s = self._render_twin()
        elif twin_age_s is None:
            twin_age_s = waited
        twin = twin or {}
        twin_live = twin_age_s is not None and twin_age_s <= self.config.dead_after_s
        out = []
        for name, shape in self.shapes.items():
            self._seq += 1
            camera = self.depth.get(name, name)  # a depth panel's capture is its camera's
            real = grab.frames.get(name) if name in self.real else None
            age = grab.ages_s.get(camera)
            real_live = (
                real is not None
                and camera not in grab.dead
                and age is not None
                and age + waited <= self.config.dead_after_s
            )
            has_twin = self.twin is not None or name in twin
            rendered = as_panel_image(twin.get(name)) if twin_live else None
            view = self._view_of(name)
            if view != "real" and not has_twin:
                view = "real"  # no twin camera for this panel: the real frame
            real = as_panel_image(real) if real_live else None
            frame = self._panel(name, shape, view, real, rendered)
            if frame.state != LIVE:
                self.no_signal += 1
            age_s = (age + waited) if view != "twin" and real_live else twin_age_s
            note = self._note(name, view, rendered)
            out.append(
                StreamFrame(
                    name, frame.image, frame.state, age_s if frame.state == LIVE else None,
                    self._seq, note, composed,
                )
            )  # fmt: skip
        return out

    def _note(self, name: str, view: str, rendered: np.ndarray | None) -> str:
        depth = f"depth {DEPTH_RANGE_M[0]:g}-{DEPTH_RANGE_M[1]:g} m" if name in self.depth else ""
        if view == "real":
            return depth
        own = self.depth.get(name, name)
        camera = self.twin.camera_for(own) if self.twin is not None else own
        what = "twin" if camera == own else f"twin {camera}"
        what = what if rendered is not None or view == "twin" else f"{what} NO SIGNAL"
        return f"{depth}, {what}" if depth else what

    def _panel(
        self,
        name: str,
        shape: tuple[int, int, int],
        view: str,
        real: np.ndarray | None,
        twin: np.ndarray | None,
    ) -> _Panel:
        """The image and state of one panel: live only if what its view needs is."""
        if view == "real" or (view == "overlay" and twin is None):
            return _Panel(real, LIVE) if real is not None else _Panel(_dead(shape, name), NO_SIGNAL)
        if view == "twin":
            if twin is None:
                return _Panel(_dead(shape, f"{name} (twin)"), NO_SIGNAL)
            return _Panel(_fit(twin, shape), LIVE)
        if real is None:  # both / overlay without the real frame: never the twin alone as live
            return _Panel(compose(_dead(shape, name), twin, "both", 0.0), NO_SIGNAL)
        if twin is None:  # both, the twin's half dead
            return _Panel(compose(real, _dead(real.shape, f"{name} (twin)"), "both", 0.0), LIVE)
        return _Panel(compose(real, twin, view, self.blend), LIVE)

    def stats(self) -> dict[str, int]:
        return {
            "offered": self.offered,
            "dropped": self.dropped,
            "sent": self.sent,
            "no_signal": self.no_signal,
            "sink_errors": self.sink_errors,
            "twin_renders": self.twin_renders,
            "twin_errors": self.twin_errors,
        }

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=5.0)


@dataclass(frozen=True)
class _Panel:
    image: np.ndarray
    state: str


def _dead(shape: tuple[int, ...], name: str) -> np.ndarray:
    return no_signal_image((int(shape[0]), int(shape[1]), 3), name)


def _fit(image: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``image`` at the panel's height and width (a twin render drawn smaller)."""
    h, w = int(shape[0]), int(shape[1])
    if image.shape[:2] == (h, w):
        return image
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
