"""The PC side of the BEAVR Quest app's sockets (see ``docs/formats.md``).

:class:`QuestReceiver` binds the PULL sockets the app PUSHes its keypoint strings and buttons
to; :class:`HeadsetImagePublisher` binds the PUB socket the app SUBscribes to for the images
it shows. Both bind on ``TransportConfig.headset_host`` (loopback unless the user passes a
LAN address). Each object owns its sockets: create, use and close it in one thread.
"""

from __future__ import annotations

import io
import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from typing import Protocol

import numpy as np
import zmq

from beavr_sim.headset.address_gate import AddressGate
from beavr_sim.headset.quest_protocol import parse_keypoints, parse_pause, parse_resolution
from beavr_sim.naming import check_name
from beavr_sim.wire.hand import SIDES, HandFrame
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.transport import Heartbeat, Liveness, bind_socket

log = logging.getLogger(__name__)

#: Receiver streams -> port names in :class:`~beavr_sim.wire.ports.PortConfig`.
QUEST_STREAMS = {
    "right": "quest_right",
    "left": "quest_left",
    "resolution": "quest_resolution",
    "pause": "quest_pause",
}
IMAGE_STREAMS = ("headset_camera", "headset_graph")
#: Most payloads taken from one socket per :meth:`QuestReceiver.poll` (keeps polls bounded).
MAX_DRAIN = 256


class FrameValidator(Protocol):
    """What :class:`QuestReceiver` needs of ``beavr_sim.headset.validation.StreamValidator``."""

    def check(self, frame: HandFrame) -> str | None: ...

    def reject(self, reason: str, detail: str = "") -> None: ...


RejectCallback = Callable[[str, str, str], None]  # (stream, reason, detail)


def _error_reason(err: ValueError) -> str:
    return getattr(err, "reason", None) or "malformed"


class QuestReceiver:
    """Receives the Quest app's hand and button streams as :class:`HandFrame` s.

    ``poll`` stamps each frame with ``t_receive = clock()`` (``t_source`` too: the app sends
    no timestamp), the latest resolution button value and the latest pause status. With
    ``latest_only`` (default) it returns at most one frame per side, the newest: payloads
    queued together carry no usable timing (e.g. a backlog from before the receiver bound),
    the older ones are parsed (so rejections are still counted) and counted in
    :attr:`superseded`. Every rejected payload (parse error, or a frame the ``validator`` refuses) is counted in
    :attr:`rejected` by reason, passed to ``validator.reject`` (parse errors only; the
    validator counts its own refusals) and to ``on_reject(stream, reason, detail)``.
    """

    def __init__(
        self,
        context: zmq.Context,
        config: TransportConfig,
        validator: FrameValidator | None = None,
        on_reject: RejectCallback | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        latest_only: bool = True,
        liveness_timeout_s: float = 0.5,
        rcvhwm: int = 100,
        gate: AddressGate | None = None,
    ):
        self.config = config
        self.latest_only = latest_only
        self.validator = validator
        self.on_reject = on_reject
        self._clock = clock
        self.resolution = "high"
        self.paused = False
        self.received: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.superseded: Counter[str] = Counter()
        self.liveness = {stream: Liveness(liveness_timeout_s, clock) for stream in QUEST_STREAMS}
        self._sockets: dict[str, zmq.Socket] = {}
        self._poller = zmq.Poller()
        try:
            for stream, port_name in QUEST_STREAMS.items():
                socket = context.socket(zmq.PULL)
                self._sockets[stream] = socket
                socket.setsockopt(zmq.LINGER, 0)
                socket.setsockopt(zmq.RCVHWM, rcvhwm)
                if gate is not None:  # peers not on the allow-list are refused at connect
                    gate.guard(socket)
                endpoint = config.endpoint(port_name, bind=True)
                try:
                    bind_socket(socket, endpoint)
                except zmq.ZMQError as err:
                    raise OSError(
                        f"cannot bind the Quest {stream} stream to {endpoint}: {err} "
                        f"(another receiver running? change PortConfig.{port_name})"
                    ) from err
                self._poller.register(socket, zmq.POLLIN)
        except BaseException:
            self.close()
            raise

    @property
    def sockets(self) -> tuple:
        """The PULL sockets (to poll with an event loop's own poller; then :meth:`poll`)."""
        return tuple(self._sockets.values())

    @property
    def endpoints(self) -> dict[str, str]:
        return {s: self.config.endpoint(p, bind=True) for s, p in QUEST_STREAMS.items()}

    def _report(self, stream: str, reason: str, detail: str, to_validator: bool) -> None:
        self.rejected[reason] += 1
        if to_validator and self.validator is not None:
            self.validator.reject(reason, f"{stream}: {detail}")
        if self.on_reject is not None:
            self.on_reject(stream, reason, detail)
        if self.validator is None and self.on_reject is None and self.rejected[reason] == 1:
            log.warning("Quest %s stream: rejected a payload (%s): %s", stream, reason, detail)

    def _drain(self, stream: str) -> list[bytes]:
        socket = self._sockets[stream]
        payloads = []
        while len(payloads) < MAX_DRAIN:
            try:
                payloads.append(socket.recv(zmq.NOBLOCK))
            except zmq.Again:
                break
        if payloads:
            self.received[stream] += len(payloads)
            self.liveness[stream].beat()
        return payloads

    def _update_controls(self) -> None:

        for payload in self._drain("resolution"):
            try:
                value = parse_resolution(payload)
            except ValueError as err:
                self._report("resolution", _error_reason(err), str(err), True)
                continue
            if value is not None:
                self.resolution = value
        for payload in self._drain("pause"):
            try:
                self.paused = parse_pause(payload)
            except ValueError as err:
                self._report("pause", _error_reason(err), str(err), True)

    def poll(self, timeout_s: float = 0.0) -> list[HandFrame]:
        """Hand frames received within ``timeout_s`` (right then left; see ``latest_only``)."""

        if self._poller is None:
            raise RuntimeError("QuestReceiver is closed")
        if not self._poller.poll(max(0, math.ceil(timeout_s * 1000))):
            return []
        self._update_controls()  # buttons first: they were sent in the same app frame
        frames = []
        for side in SIDES:
            parsed = []
            for payload in self._drain(side):
                t_receive = self._clock()
                try:
                    parsed.append(
                        parse_keypoints(
                            payload, side, t_receive, resolution=self.resolution, paused=self.paused
                        )
                    )
                except ValueError as err:
                    self._report(side, _error_reason(err), str(err), True)
            if self.latest_only and len(parsed) > 1:
                self.superseded[side] += len(parsed) - 1
                parsed = parsed[-1:]
            for frame in parsed:
                if self.validator is not None:
                    reason = self.validator.check(frame)
                    if reason is not None:
                        self._report(side, reason, f"t_source {frame.t_source!r}", False)
                        continue
                frames.append(frame)
        return frames

    def alive(self, stream: str) -> bool:
        """Whether the app sent on ``stream`` within the liveness timeout."""
        return self.liveness[check_name("Quest stream", stream, QUEST_STREAMS)].alive()

    def close(self) -> None:
        for socket in self._sockets.values():
            if not socket.closed:
                socket.close(linger=0)
        self._poller = None

    def __enter__(self) -> QuestReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def encode_jpeg(image: np.ndarray, quality: int = 80) -> bytes:
    """JPEG bytes of an ``(H, W, 3)`` or ``(H, W)`` uint8 image."""
    from PIL import Image  # local: heavy (Pillow, ~15-30 ms, only when images are streamed)

    image = np.asarray(image)
    if (
        image.dtype != np.uint8
        or image.ndim not in (2, 3)
        or (image.ndim == 3 and image.shape[2] != 3)
    ):
        raise ValueError(
            f"image must be uint8 of shape (H, W, 3) or (H, W), got {image.dtype} {image.shape}"
        )
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


class HeadsetImagePublisher:
    """Sends images to the headset: one single-frame JPEG message each, at most ``rate_hz``.

    Binds PUB on ``stream`` (``"headset_camera"`` or ``"headset_graph"``). The send queue is
    short (``sndhwm``): a headset that falls behind loses images rather than lagging.
    """

    def __init__(
        self,
        context: zmq.Context,
        config: TransportConfig,
        rate_hz: float = 30.0,
        jpeg_quality: int = 80,
        *,
        stream: str = "headset_camera",
        sndhwm: int = 2,
        clock: Callable[[], float] = time.monotonic,
    ):
        check_name("headset image stream", stream, IMAGE_STREAMS)
        if (
            isinstance(jpeg_quality, bool)
            or not isinstance(jpeg_quality, int)
            or not (1 <= jpeg_quality <= 95)
        ):
            raise ValueError(f"jpeg_quality must be an int in 1..95, got {jpeg_quality!r}")
        self._pace = Heartbeat(rate_hz, clock)
        self.jpeg_quality = jpeg_quality
        self.sent = 0
        self.endpoint = config.endpoint(stream, bind=True)
        self._socket = context.socket(zmq.PUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.SNDHWM, sndhwm)
        try:
            bind_socket(self._socket, self.endpoint)
        except zmq.ZMQError as err:
            self._socket.close(linger=0)
            raise OSError(f"cannot bind the {stream} stream to {self.endpoint}: {err}") from err

    def publish(self, image: np.ndarray) -> bool:
        """Encode and send ``image`` unless one was sent less than a period ago; True if sent."""
        if self._socket.closed:
            raise RuntimeError(f"HeadsetImagePublisher on {self.endpoint} is closed")
        if not self._pace.due():
            return False
        self._socket.send(encode_jpeg(image, self.jpeg_quality))
        self.sent += 1
        return True

    def close(self) -> None:
        if not self._socket.closed:
            self._socket.close(linger=0)

    def __enter__(self) -> HeadsetImagePublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
