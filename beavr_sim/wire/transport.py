"""ZeroMQ transport of typed messages between pipeline processes.

Rules:

- One ``zmq.Context`` per process, created by the caller (``zmq.Context()``) and passed in;
  nothing here creates one at import time.
- Each :class:`Publisher` / :class:`Subscriber` owns one socket and must be created, used and
  closed by **one thread** (ZMQ sockets are not thread-safe). Sockets close with linger 0.
- A message on the wire is one single-part frame ``topic + b" " + msgpack``, so a SUB
  filter on ``topic + b" "`` matches one topic exactly and ``ZMQ_CONFLATE`` (single-part
  only) can keep just the newest message.
- Latest-only streams (hand frames, commands, robot state) use one conflating
  :class:`Subscriber` per topic: conflation keeps one message per socket, so a conflating
  socket may subscribe to exactly one topic. Streams where every message counts (session
  commands) use ``conflate=False``.
- The publisher is an XPUB socket: it sees subscriptions, so :meth:`Publisher.wait_for_subscribers`
  avoids losing the first messages to ZMQ's slow-joiner problem.
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import zmq

from beavr_sim.wire.messages import Message, MessageError, decode, encode

log = logging.getLogger(__name__)

TOPIC_SEPARATOR = b" "
_TOPIC = re.compile(rb"[A-Za-z0-9_./-]+")
LIVENESS_STATES = ("waiting", "alive", "dead")


def check_topic(topic: bytes) -> bytes:
    """Return ``topic`` if it is valid (non-empty ASCII letters, digits, ``_ . / -``)."""
    if not isinstance(topic, bytes) or not _TOPIC.fullmatch(topic):
        raise ValueError(
            f"topic must be non-empty bytes of letters, digits and '_./-' (e.g. b'right'), "
            f"got {topic!r}"
        )
    return topic


def pack(topic: bytes, msg: Message) -> bytes:
    """The single wire frame of ``msg`` on ``topic``."""
    return check_topic(topic) + TOPIC_SEPARATOR + encode(msg)


def unpack(data: bytes, expected_type: Any = Message) -> tuple[bytes, Any]:
    """``(topic, message)`` from a wire frame; raises :class:`MessageError`."""
    topic, sep, payload = bytes(data).partition(TOPIC_SEPARATOR)
    if not sep or not _TOPIC.fullmatch(topic):
        raise MessageError(f"frame does not start with 'topic ': {bytes(data[:32])!r}")
    return topic, decode(payload, expected_type)


def bind_socket(socket: zmq.Socket, endpoint: str, retry_s: float = 1.0) -> str:
    """Bind ``socket``, retrying "address in use" for ``retry_s`` (ZMQ closes sockets in the
    background, so a port freed in this process a moment ago may still be held); returns the
    endpoint bound (wildcard port resolved). Raises ``zmq.ZMQError``."""
    deadline = time.monotonic() + retry_s
    while True:
        try:
            socket.bind(endpoint)
            return socket.getsockopt_string(zmq.LAST_ENDPOINT)
        except zmq.ZMQError as err:
            if err.errno != zmq.EADDRINUSE or time.monotonic() >= deadline:
                raise
            time.sleep(0.02)


class Liveness:
    """Whether a producer is alive, from the arrival times of its messages.

    ``state``: ``"waiting"`` before the first message, ``"alive"`` while the last one is at
    most ``timeout_s`` old, ``"dead"`` after that.
    """

    def __init__(self, timeout_s: float, clock: Callable[[], float] = time.monotonic):
        if not timeout_s > 0 or not math.isfinite(timeout_s):
            raise ValueError(f"liveness timeout_s must be a positive number, got {timeout_s!r}")
        self.timeout_s = float(timeout_s)
        self._clock = clock
        self.last_beat: float | None = None

    def beat(self, now: float | None = None) -> None:
        self.last_beat = self._clock() if now is None else now

    def age_s(self, now: float | None = None) -> float:
        """Seconds since the last message (inf before the first)."""
        if self.last_beat is None:
            return math.inf
        return (self._clock() if now is None else now) - self.last_beat

    def state(self, now: float | None = None) -> str:
        if self.last_beat is None:
            return "waiting"
        return "alive" if self.age_s(now) <= self.timeout_s else "dead"

    def alive(self, now: float | None = None) -> bool:
        return self.state(now) == "alive"


class Heartbeat:
    """Paces a producer's state stream: :meth:`due` is true at most ``rate_hz`` times a second.

    A producer publishes its latest state whenever ``due()`` (even when nothing changed), so
    consumers can tell it is alive with a :class:`Liveness` of a few periods.
    """

    def __init__(self, rate_hz: float, clock: Callable[[], float] = time.monotonic):
        if not rate_hz > 0 or not math.isfinite(rate_hz):
            raise ValueError(f"heartbeat rate_hz must be a positive number, got {rate_hz!r}")
        self.period_s = 1.0 / rate_hz
        self._clock = clock
        self._next: float | None = None

    def due(self, now: float | None = None) -> bool:
        now = self._clock() if now is None else now
        if self._next is not None and now < self._next - 1e-9:  # 1 ns: float round-off
            return False
        if self._next is None or self._next + self.period_s <= now:
            self._next = now + self.period_s  # first beat, or after a stall: no burst
        else:
            self._next += self.period_s
        return True


class _Socket:
    """Shared close / context-manager behaviour."""

    _socket: zmq.Socket

    @property
    def closed(self) -> bool:
        return self._socket.closed

    @property
    def endpoint(self) -> str:
        """The endpoint actually bound / connected (wildcard ports resolved)."""
        return self._endpoint

    def close(self) -> None:
        if not self._socket.closed:
            self._socket.close(linger=0)

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._socket.closed:
            raise RuntimeError(f"{type(self).__name__} on {self._endpoint} is closed")

    def _attach(self, endpoint: str, bind: bool) -> None:
        try:
            if bind:
                endpoint = bind_socket(self._socket, endpoint)
            else:
                self._socket.connect(endpoint)
        except zmq.ZMQError as err:
            self._socket.close(linger=0)
            verb = "bind" if bind else "connect"
            raise OSError(f"cannot {verb} {type(self).__name__} to {endpoint}: {err}") from err
        self._endpoint = endpoint


class Publisher(_Socket):
    """Publishes typed messages on an XPUB socket (owned by one thread).

    ``endpoint``: e.g. ``TransportConfig.endpoint("robot_state", bind=True)``; a wildcard port
    (``tcp://127.0.0.1:*``) binds a free one, see :attr:`endpoint`. Sends never block: a
    subscriber more than ``sndhwm`` messages behind loses messages.
    """

    def __init__(
        self, context: zmq.Context, endpoint: str, bind: bool = True, *, sndhwm: int = 100
    ):
        self._endpoint = endpoint
        self._socket = context.socket(zmq.XPUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.SNDHWM, sndhwm)
        # Pass every (un)subscription up, so subscribers can be counted.
        self._socket.setsockopt(zmq.XPUB_VERBOSER, 1)
        self._subscriptions: Counter[bytes] = Counter()
        self.sent = 0
        self._attach(endpoint, bind)

    def _drain_subscriptions(self) -> None:
        while True:
            try:
                event = self._socket.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            if not event:
                continue
            topic = event[1:].removesuffix(TOPIC_SEPARATOR)
            if event[0] == 1:
                self._subscriptions[topic] += 1
            elif event[0] == 0 and self._subscriptions[topic] > 0:
                self._subscriptions[topic] -= 1

    def subscriber_count(self, topic: bytes | None = None) -> int:
        """Live subscriptions to ``topic`` (plus those to every topic), or to anything."""
        self._check_open()
        self._drain_subscriptions()
        if topic is None:
            return sum(self._subscriptions.values())
        return self._subscriptions[check_topic(topic)] + self._subscriptions[b""]

    def wait_for_subscribers(
        self, n: int = 1, timeout_s: float = 5.0, topic: bytes | None = None
    ) -> bool:
        """Block until ``n`` subscriptions (to ``topic`` if given) are live; False on timeout.

        A :class:`Subscriber` subscribes once per topic, so for single-topic subscribers this
        counts subscribers. Once this returns True, the next :meth:`send` reaches them.
        """
        deadline = time.monotonic() + timeout_s
        while self.subscriber_count(topic) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self._socket.poll(max(1, int(remaining * 1000)), zmq.POLLIN)
        return True

    def send(self, topic: bytes, msg: Message) -> None:
        """Publish ``msg`` on ``topic`` (never blocks)."""
        self._check_open()
        frame = pack(topic, msg)
        self._drain_subscriptions()
        self._socket.send(frame)
        self.sent += 1


class Subscriber(_Socket):
    """Receives typed messages on a SUB socket (owned by one thread).

    ``topics``: the topics to receive (bytes or a sequence; empty = every topic, only without
    conflation). ``msg_type``: the message type expected (or a union). With ``conflate=True``
    the socket keeps only the newest message (one topic only). Malformed messages are
    dropped, counted in :attr:`dropped` and logged; they never raise. Every valid message is
    a beat of :attr:`liveness`, timed by ``clock`` (monotonic seconds; tests inject one).
    """

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        topics: bytes | Sequence[bytes],
        msg_type: Any = Message,
        *,
        conflate: bool = True,
        bind: bool = False,
        liveness_timeout_s: float = 0.5,
        rcvhwm: int = 1000,
        clock: Callable[[], float] = time.monotonic,
    ):
        topics = (topics,) if isinstance(topics, bytes) else tuple(topics)
        for topic in topics:
            check_topic(topic)
        if conflate and len(topics) != 1:
            raise ValueError(
                f"a conflating Subscriber keeps one message per socket, so it takes exactly one "
                f"topic, got {list(topics)}; use one Subscriber per topic or conflate=False"
            )
        self.topics = topics
        self.msg_type = msg_type
        self.liveness = Liveness(liveness_timeout_s, clock)
        self.received = 0
        self.dropped = 0
        self.last_topic: bytes | None = None
        self.last_error: str | None = None
        self._last_log = -math.inf
        self._endpoint = endpoint
        self._socket = context.socket(zmq.SUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        if conflate:
            self._socket.setsockopt(zmq.CONFLATE, 1)
        else:
            self._socket.setsockopt(zmq.RCVHWM, rcvhwm)
        for topic in topics or (b"",):
            self._socket.setsockopt(zmq.SUBSCRIBE, topic + TOPIC_SEPARATOR if topic else b"")
        self._attach(endpoint, bind)

    @property
    def socket(self) -> zmq.Socket:
        """The socket, for registering with a ``zmq.Poller`` in the owning thread."""
        return self._socket

    def _drop(self, error: MessageError) -> None:
        self.dropped += 1
        self.last_error = str(error)
        now = time.monotonic()
        if now - self._last_log >= 1.0:  # at most one warning a second
            self._last_log = now
            log.warning(
                "dropped malformed message on %s (%d so far): %s",
                self._endpoint,
                self.dropped,
                error,
            )

    def _recv_one(self) -> Any | None:
        """One valid message without waiting, or None when the queue is empty."""
        while True:
            try:
                data = self._socket.recv(zmq.NOBLOCK, copy=True)
            except zmq.Again:
                return None
            try:
                topic, msg = unpack(data, self.msg_type)
            except MessageError as err:
                self._drop(err)
                continue
            self.received += 1
            self.last_topic = topic
            self.liveness.beat()
            return msg

    def recv(self, timeout_s: float = 0.0) -> Any | None:
        """The next valid message, waiting up to ``timeout_s``; None if none came."""
        self._check_open()
        deadline = time.monotonic() + timeout_s
        while True:
            msg = self._recv_one()
            if msg is not None:
                return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._socket.poll(max(1, math.ceil(remaining * 1000)), zmq.POLLIN)

    def recv_latest(self, timeout_s: float = 0.0) -> Any | None:
        """The newest valid message (older queued ones are discarded); None if none came."""
        latest = self.recv(timeout_s)
        while latest is not None:
            newer = self._recv_one()
            if newer is None:
                break
            latest = newer
        return latest

    def alive(self) -> bool:
        """Whether :meth:`recv` took a valid message within the liveness timeout."""
        return self.liveness.alive()
