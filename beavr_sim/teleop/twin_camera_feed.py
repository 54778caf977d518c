"""The twin's renders for the streamed camera panels (``--camera-stream-hz``): what a panel's
``twin``, ``both`` and ``overlay`` views show, and the panels of a session without real cameras.

Contract: the control thread's only work is the tick listener :meth:`TwinCameraFeed.__call__`:
at most ``rate_hz`` times per wall second it copies the scene's pose (:class:`ScenePose`: a few
small arrays) into a one-slot mailbox; it never renders, never blocks and never raises. The
camera stream's worker thread calls :meth:`TwinCameraFeed.render`: it poses its own ``MjData``
from the newest copy and draws each panel's twin camera (renderers created, used and closed on
that thread), returning the copy's age, so a twin that stopped ticking reads NO SIGNAL in the
panels instead of a frozen render shown as live.

A panel's twin camera is the scene camera of the panel's name (a real camera's twin, placed at
its pose by ``--camera-poses``, or the scene's ``front`` / ``overhead``), else ``fallback``
(the headset's camera). Renders are at the panel's size, scaled down to fit the scene's
offscreen buffer (the stream scales them up to the real frame). A one-channel shape asks for
the twin's depth (HxWx1 float32 metres, MuJoCo's depth buffer) of a depth panel ``NAME_depth``:
camera ``NAME``'s twin camera, drawn from the same pose copy.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence

import mujoco
import numpy as np

from beavr_sim.envs.cameras import OffscreenCameras
from beavr_sim.naming import check_name
from beavr_sim.teleop.images import ScenePose, headset_camera

#: A twin-only panel's size (HxW) when its camera gives none (a placed camera's intrinsics do).
TWIN_PANEL_SIZE = (480, 640)
#: A depth panel's suffix after its camera's name (LeRobot's depth feature name, ``NAME_depth``).
DEPTH_SUFFIX = "_depth"


class TwinCameraFeed:
    """Tick listener (control thread) and twin-render source (stream thread) for the panels.

    ``model``: the twin's render model; ``data``: the env's ``MjData`` (read on the control
    thread only, in the tick); ``fallback``: the camera drawn for a panel whose name is no
    camera of the scene; ``rate_hz``: pose copies per wall second at most."""

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        fallback: str,
        rate_hz: float,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"twin camera feed rate must be > 0, got {rate_hz}")
        self.model = model
        self.cameras = tuple(model.camera(i).name for i in range(model.ncam))
        self.fallback = check_name("camera", fallback, self.cameras)
        self.period_s = 1.0 / float(rate_hz)
        self._source = data
        self._clock = clock
        self._lock = threading.Lock()
        self._pose: tuple[ScenePose, float] | None = None
        self._due = 0.0
        #: Pose copies taken (control thread) and panels rendered (stream thread).
        self.copies = 0
        self.rendered = 0
        # Stream thread only:
        self._data: mujoco.MjData | None = None
        self._posed: tuple[ScenePose, float] | None = None
        self._renderers: dict[tuple[int, int], OffscreenCameras] = {}

    def camera_for(self, panel: str) -> str:
        """The twin camera drawn for ``panel``."""
        return panel if panel in self.cameras else self.fallback

    def panel_shape(self, panel: str) -> tuple[int, int, int]:
        """A twin-only panel's shape: its camera's resolution where it has one (a placed
        camera's intrinsics), else :data:`TWIN_PANEL_SIZE`."""
        cam = self.model.camera(self.camera_for(panel)).id
        width, height = (int(v) for v in self.model.cam_resolution[cam])
        if width > 1 and height > 1:
            return (height, width, 3)
        return (*TWIN_PANEL_SIZE, 3)

    def __call__(self, tick) -> None:
        """The control thread's tick: copy the pose when one is due (never more)."""
        now = self._clock()
        if now < self._due:
            return
        self._due = now + self.period_s
        pose = ScenePose.of(self._source)
        with self._lock:
            self._pose = (pose, now)
        self.copies += 1

    def render(
        self, shapes: Mapping[str, tuple[int, int, int]]
    ) -> tuple[dict[str, np.ndarray], float | None]:
        """Each panel's twin render from the newest pose copy (its depth for a one-channel
        shape), and that copy's age (s); ({}, None) before the first tick. Stream thread only."""
        with self._lock:
            slot = self._pose
        if slot is None:
            return {}, None
        if slot is not self._posed:
            if self._data is None:
                self._data = mujoco.MjData(self.model)
            pose = slot[0]
            self._data.qpos[:] = pose.qpos
            self._data.mocap_pos[:] = pose.mocap_pos
            self._data.mocap_quat[:] = pose.mocap_quat
            mujoco.mj_forward(self.model, self._data)
            self._posed = slot
        images = {}
        for panel, shape in shapes.items():
            size = self._fit(int(shape[0]), int(shape[1]))
            cameras = self._renderers.get(size)
            if cameras is None:
                cameras = self._renderers[size] = OffscreenCameras(self.model, *size)
            if len(shape) == 3 and int(shape[2]) == 1:  # a depth panel: its camera's depth
                camera = self.camera_for(panel.removesuffix(DEPTH_SUFFIX))
                images[panel] = cameras.render_depth(self._data, camera)
            else:
                images[panel] = cameras.render(self._data, self.camera_for(panel))
            self.rendered += 1
        return images, max(0.0, self._clock() - slot[1])

    def _fit(self, height: int, width: int) -> tuple[int, int]:
        """(height, width) scaled down, aspect kept, into the offscreen buffer."""
        off_h, off_w = self.model.vis.global_.offheight, self.model.vis.global_.offwidth
        scale = min(1.0, off_h / height, off_w / width)
        return max(1, int(height * scale)), max(1, int(width * scale))

    def close(self) -> None:
        """Release the renderers (on the thread that rendered)."""
        for cameras in self._renderers.values():
            cameras.close()
        self._renderers.clear()


def twin_feed(
    env, rate_hz: float, placed: Sequence[str] = ()
) -> tuple[TwinCameraFeed, tuple[str, ...]]:
    """The twin's renders for a session's camera panels (both layouts): the feed (a tick /
    ``after_step`` hook to add) and the twin-only panels shown when the session has no real
    camera: the cameras ``--camera-poses`` places (``placed``), else the headset's camera."""
    feed = TwinCameraFeed(env.render_model, env.data, headset_camera(env.embodiment), rate_hz)
    return feed, twin_panel_names(env, placed)


def twin_panel_names(env, placed: Sequence[str] = ()) -> tuple[str, ...]:
    """The twin-only panels of a session without real cameras: the cameras ``--camera-poses``
    places (``placed``), else the headset's camera."""
    return tuple(placed) or (headset_camera(env.embodiment),)
