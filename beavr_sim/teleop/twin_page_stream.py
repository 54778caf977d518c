"""``--source webxr --multiprocess`` without ``--headless``: the twin drawn on the WebXR page.

The page's server is the operator process's, the twin is the twin process's. The twin sends
what the page draws on the state stream: its scene once (:class:`TwinPageFeed`'s
:class:`~beavr_sim.wire.messages.TwinSceneMsg`, topic :data:`SCENE_TOPIC`, sent right after
the stream's readiness handshake) and its moving geoms' poses at most ``rate_hz`` per wall
second, the page's twin rate in one process (:class:`~beavr_sim.wire.messages.TwinPosesMsg`,
topic :data:`POSES_TOPIC`, copied on the twin stage's ``after_step`` hook, sent after the
state; the newest only). The operator's :class:`PageTwinRelay` hands both to its page server
with the same ``publish("scene" | "twin", message)`` one process uses, the ``twin`` message
completed there with what the operator knows (whether it holds paused, why each effector
holds: :func:`~beavr_sim.headset.webxr_scene.page_status`).

Contract: :class:`TwinPageStream` is frozen (passed whole to the spawned twin); the feed never
raises into the step (a stage hook), copies a few hundred numbers per due step and encodes the
scene once; the relay never blocks (the page server's thread sends), never raises (a scene
that is no page ``scene`` message is dropped and counted) and sends no pose before the scene.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import zmq

from beavr_sim.headset.webxr_scene import RateGate, TwinGeometry, page_status, twin_message
from beavr_sim.headset.webxr_server import encode_page_message
from beavr_sim.wire.messages import TwinPosesMsg, TwinSceneMsg
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.records import JointCommand, TwinState
from beavr_sim.wire.transport import Subscriber

#: The state stream's topics of the page's twin: its scene (once) and its poses.
SCENE_TOPIC = b"twin_scene"
POSES_TOPIC = b"twin_poses"


@dataclass(frozen=True)
class TwinPageStream:
    """The twin process's part of the page's twin: ``rate_hz`` pose updates per wall second
    at most (``WebXRConfig.twin_rate_hz``, the rate one process sends the page)."""

    rate_hz: float

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ValueError(f"the page's twin rate must be > 0, got {self.rate_hz}")


class TwinPageFeed:
    """The twin process's ``after_step`` hook: the scene of ``env``'s render model (built at
    construction, from the env's data as it is), then the moving geoms' poses of a due step
    (:meth:`take`: the newest, once)."""

    def __init__(
        self, env, config: TwinPageStream, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.geometry = TwinGeometry.from_model(env.render_model)
        self.data = env.data
        self.gate = RateGate(config.rate_hz, clock)
        info = {"task": env.task.name, "embodiment": env.embodiment.label}
        message = self.geometry.scene_message(env.data, **info)
        self.scene = TwinSceneMsg(message=encode_page_message(message))
        self._newest: TwinPosesMsg | None = None

    def __call__(self, state: TwinState) -> None:
        if self.gate.due():
            self._newest = TwinPosesMsg(t=state.t, pose=self.geometry.moving_poses(self.data))

    def take(self) -> TwinPosesMsg | None:
        newest, self._newest = self._newest, None
        return newest


class PageTwinRelay:
    """The operator process's end: subscribes to the twin's scene and poses (both
    conflated: the newest only) and hands them to ``server`` (the page server) as one process
    does, the ``twin`` message's status from ``operator`` (read only) and the newest command
    of each effector (:meth:`note`)."""

    def __init__(self, context: zmq.Context, transport: TransportConfig, server, operator) -> None:
        endpoint = transport.endpoint("robot_state", bind=False)
        self.server = server
        self.operator = operator
        self.scene = Subscriber(context, endpoint, SCENE_TOPIC, TwinSceneMsg)
        self.poses = Subscriber(context, endpoint, POSES_TOPIC, TwinPosesMsg)
        self.commands: dict[str, JointCommand] = {}
        self.scene_sent = False
        self.poses_sent = 0
        #: Scene messages that were no page ``scene`` message (not JSON, another type).
        self.bad_scenes = 0

    @property
    def sockets(self) -> tuple[zmq.Socket, ...]:
        return (self.scene.socket, self.poses.socket)

    def note(self, commands: Mapping[str, JointCommand]) -> None:
        """The operator's newest commands (why each effector holds)."""
        self.commands.update(commands)

    def relay(self) -> None:
        """Hand what arrived to the page server (never blocks)."""
        scene = self.scene.recv(0.0)
        message = None
        if scene is not None:
            try:
                message = json.loads(scene.message)
            except ValueError:
                pass
            if not isinstance(message, dict) or message.get("type") != "scene":
                self.bad_scenes += 1  # dropped, never handed to the page
                message = None
        if message is not None:
            self.server.publish("scene", message)
            self.scene_sent = True
        poses = self.poses.recv_latest(0.0)
        if poses is not None and self.scene_sent:
            status = page_status(self.commands, bool(self.operator.paused))
            self.server.publish("twin", twin_message(poses.t, poses.pose, **status))
            self.poses_sent += 1

    def close(self) -> None:
        self.scene.close()
        self.poses.close()
