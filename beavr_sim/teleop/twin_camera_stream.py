"""``--camera-stream-hz`` under ``--multiprocess``: the camera panels streamed from the twin process.

The twin process holds what the panels show (the real cameras, read next to the recorder, and
the twin's scene) and two of their viewers (the browser view, the Quest app's image socket), so
the stream runs there: :func:`attach_camera_stream` builds the same
:func:`~beavr_sim.teleop.camera_viewers.start_camera_stream` as one process, its twin renders
fed by a :class:`~beavr_sim.teleop.twin_camera_feed.TwinCameraFeed` on the twin stage's
``after_step`` hook (the step only copies the pose, at the stream's rate). The WebXR page's
panel is not streamed here (its server is the operator process's): ``SessionOptions`` refuses
``--source webxr`` with it.

Contract: :class:`TwinCameraStream` is frozen (passed whole to the spawned twin); the returned
closer stops the stream before the cameras it reads and the viewers it sends to are closed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from beavr_sim.teleop.camera_viewers import CameraViewers, start_camera_stream
from beavr_sim.teleop.twin_camera_feed import twin_feed


@dataclass(frozen=True)
class TwinCameraStream:
    """The twin process's camera stream: ``rate_hz`` panels per second, the ``view`` asked
    (``auto`` or one of ``beavr_sim.cameras.stream.VIEWS``), the twin-only panels' names (the
    cameras ``--camera-poses`` places; none: the headset's camera), and whether the Quest
    app's camera panel shows the first real camera (in place of the twin's headset images)."""

    rate_hz: float
    view: str = "auto"
    placed: tuple[str, ...] = ()
    quest: bool = False
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


def attach_camera_stream(
    config: TwinCameraStream, env, stage, real, view=None, quest=None
) -> Callable[[], None]:
    """Stream ``real``'s cameras (a connected ``RealCameras`` or None) and the twin's renders
    of ``env`` to ``view`` (a ``TwinView``) and ``quest`` (a ``HeadsetImagePublisher``, used
    when ``config.quest``); the feed follows ``stage``'s steps. Returns the stream's closer."""
    feed, panels = twin_feed(env, config.rate_hz, config.placed)
    stage.after_step.append(feed)
    viewers = CameraViewers(
        view=view,
        quest=quest if config.quest else None,
        twin=feed,
        twin_panels=panels,
    )
    stream = start_camera_stream(real, config.stream_config(), viewers)

    return stream.close if stream is not None else lambda: None  # (it closes the feed)
