"""The WebXR page's server: static page (HTTP, or HTTPS off loopback) and one WebSocket.

``websockets`` (>= 13, its asyncio API) serves both: the page's files from
``beavr_sim/headset/webxr_static`` through ``process_request`` and the WebSocket on
:data:`WS_PATH`. It runs in a thread of its own with its own event loop, never on the control
thread:

- page -> detector: each message is parsed on the server thread (:mod:`webxr_protocol`) and
  its :class:`HandFrame` s handed over through a bounded queue; the control thread takes them
  with :meth:`WebXRServer.take`, which runs the :class:`StreamValidator` (order, duplicates)
  and counts every rejection there, parse errors included, as the Quest path does. One page
  drives at a time (the first to send hands; the next one once it closes); hands from a second
  page are rejected (``second_page``).
- detector -> page: :meth:`WebXRServer.publish` (any thread) hands a message to the server
  thread, which encodes it and sends it to every open page whose send buffer is not backed up
  (the twin's scene once per connection, its poses at a modest rate, see ``webxr_scene``).

Bound to 127.0.0.1 unless given another host. Pages from another origin may not open the
WebSocket (a browser sends ``Origin``; it must match ``Host``).
"""

from __future__ import annotations

import asyncio
import collections
import ipaddress
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import msgspec
import numpy as np

from beavr_sim.headset.validation import StreamValidator
from beavr_sim.headset.webxr_protocol import (
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    HandsMessage,
    HelloMsg,
    SessionMsg,
    WebXRProtocolError,
    hand_frames,
    parse_message,
)
from beavr_sim.headset.webxr_tls import ensure_certificate, local_ipv4_addresses, server_ssl_context
from beavr_sim.naming import check_name
from beavr_sim.wire.access import BAD_TOKEN, NO_TOKEN, SessionToken, is_loopback
from beavr_sim.wire.hand import HandFrame
from beavr_sim.wire.ports import PortConfig

log = logging.getLogger(__name__)

#: Why a WebSocket was refused before its first message (counted in the summary's
#: ``rejected_by_reason`` beside the frames' reasons).
HANDSHAKE_REFUSALS = ("cross_origin", NO_TOKEN, BAD_TOKEN)
STATIC_DIR = Path(__file__).with_name("webxr_static")
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
}
WS_PATH = "/ws"
TLS_MODES = ("auto", "on", "off")
#: Events (frames of one message, rejections) waiting for the control thread at most; older
#: ones are dropped and counted when it falls this far behind.
MAX_PENDING_EVENTS = 256
_HOST_NAME = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?")


@dataclass(frozen=True)
class WebXRConfig:
    """Where and how the page is served.

    ``host``: 127.0.0.1 (default: this machine only) or a LAN address / ``0.0.0.0`` for a
    headset on the network. ``tls``: ``auto`` (HTTPS unless the host is loopback: WebXR needs
    a secure context, and only localhost is one over plain HTTP), ``on`` or ``off``.
    ``cert_dir``: where the self-signed certificate is cached (default
    ``~/.cache/beavr_sim/webxr-tls``). ``port`` 0: any free port.
    """

    host: str = "127.0.0.1"
    port: int = PortConfig().webxr
    tls: str = "auto"
    cert_dir: Path | None = None
    max_message_bytes: int = MAX_MESSAGE_BYTES
    #: Twin poses sent to the page per second at most.
    twin_rate_hz: float = 15.0
    #: A page whose unsent data exceeds this many bytes skips twin updates until it catches up.
    max_buffered_bytes: int = 256 * 1024
    #: The session token WebSockets must present (``None``: the loopback rule for ``host``
    #: with a fresh token, see :class:`beavr_sim.wire.access.SessionToken`).
    token: SessionToken | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.host == "*":
            raise ValueError("webxr host: use '0.0.0.0' to listen on every interface, not '*'")
        if not isinstance(self.host, str) or not _HOST_NAME.fullmatch(self.host):
            raise ValueError(
                f"webxr host must be an IPv4 address or a host name (e.g. '127.0.0.1', "
                f"'0.0.0.0', '192.168.1.20'), got {self.host!r}"
            )
        if self.host.replace(".", "").isdigit():
            try:
                ipaddress.IPv4Address(self.host)
            except ValueError:
                raise ValueError(f"webxr host {self.host!r} is not a valid IPv4 address") from None
        port = self.port
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"webxr port must be an integer in 0..65535, got {port!r}")
        check_name("webxr tls mode", self.tls, TLS_MODES)
        if not self.twin_rate_hz > 0:
            raise ValueError(f"twin_rate_hz must be positive, got {self.twin_rate_hz!r}")
        if self.token is None:
            object.__setattr__(self, "token", SessionToken.for_host(self.host))
        for name in ("max_message_bytes", "max_buffered_bytes"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")

    @property
    def use_tls(self) -> bool:
        return self.tls == "on" or (self.tls == "auto" and not is_loopback(self.host))


@dataclass
class WebXRStats:
    """Counters of the server (written on its thread; read anywhere)."""

    connections: int = 0
    messages: int = 0
    hand_messages: int = 0
    #: Parse errors and refused messages by reason (the validator's refusals are in the
    #: validator's own counts).
    rejected: collections.Counter = field(default_factory=collections.Counter)
    #: Events dropped because the control thread fell behind.
    dropped_events: int = 0
    twin_sent: int = 0
    twin_skipped: int = 0
    sessions_started: int = 0
    #: ``time.monotonic()`` of the last hands messages (frames per second).
    hand_times: collections.deque = field(default_factory=lambda: collections.deque(maxlen=4096))
    agent: str = ""


def _load_static() -> dict[str, tuple[bytes, str]]:
    files = {}
    for path in sorted(STATIC_DIR.iterdir()):
        if path.is_file() and path.suffix in CONTENT_TYPES:
            files[path.name] = (path.read_bytes(), CONTENT_TYPES[path.suffix])
    if "index.html" not in files:
        raise FileNotFoundError(f"the WebXR page is missing: {STATIC_DIR / 'index.html'}")
    return files


def encode_page_message(obj: object) -> str:
    """A page message as JSON text (numpy arrays as lists)."""

    def enc_hook(o: object) -> object:
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise NotImplementedError(f"cannot encode {type(o).__name__}")

    return msgspec.json.encode(obj, enc_hook=enc_hook).decode()


class WebXRServer:
    """Serves the page; :meth:`take` returns the hand frames that arrived (control thread).

    Starts its thread at construction and returns once it listens (raises ``OSError`` when it
    cannot bind). ``validator`` (a ``StreamValidator``) is only ever used by :meth:`take`.
    """

    def __init__(
        self,
        config: WebXRConfig | None = None,
        validator: StreamValidator | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        start_timeout_s: float = 10.0,
    ):
        self.config = config or WebXRConfig()
        self.validator = validator
        self.stats = WebXRStats()
        #: Frames the validator refused, by reason (control thread).
        self.refused: collections.Counter = collections.Counter()
        self._clock = clock
        self._files = _load_static()
        self._events: collections.deque = collections.deque()
        self._arrived = threading.Event()
        self._connections: set = set()
        self._driver = None
        self._latest: dict[str, str] = {}  # kind -> last message sent (scene, twin)
        self._welcome: dict = {"v": PROTOCOL_VERSION, "type": "welcome", "server": "beavr_sim"}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.port: int | None = None
        ssl_context = None
        if self.config.use_tls:
            cert, key = ensure_certificate(self.config.host, self.config.cert_dir)
            ssl_context = server_ssl_context(cert, key)
        self._thread = threading.Thread(
            target=self._run, args=(ssl_context,), name="webxr-server", daemon=True
        )
        self._thread.start()
        if not self._ready.wait(start_timeout_s):
            self.close()
            raise TimeoutError(f"the WebXR server did not start within {start_timeout_s} s")
        if self._error is not None:
            self._thread.join(timeout=5.0)
            raise OSError(
                f"cannot serve the WebXR page on {self.config.host}:{self.config.port}: "
                f"{self._error} (another server running? choose --webxr-port)"
            ) from self._error

    # ------------------------------------------------------------------ any thread
    @property
    def url(self) -> str:
        scheme = "https" if self.config.use_tls else "http"
        host = self.config.host
        if host == "0.0.0.0":
            host = next(iter(local_ipv4_addresses()), "127.0.0.1")
        return f"{scheme}://{host}:{self.port}/{self.config.token.url_suffix()}"

    @property
    def driving(self) -> bool:
        """Whether a page is sending hands."""
        return self._driver is not None

    def set_info(self, **info: object) -> None:
        """Fields added to the ``welcome`` message each page gets (task, embodiment, rates)."""
        self._welcome.update(info)

    def publish(self, kind: str, message: dict) -> None:
        """Send ``message`` (numpy arrays allowed) to every open page; the latest one of each
        ``kind`` also goes to pages that connect later. Never blocks."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._send_all, kind, message)
        except RuntimeError:  # the loop closed meanwhile
            pass

    def close(self) -> None:
        """Stop serving: pages are disconnected (1001 going away), the thread ends."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:
                pass
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                log.warning("the WebXR server thread did not stop within 5 s")

    # ------------------------------------------------------------------ control thread
    def take(self, timeout_s: float = 0.0) -> list[HandFrame]:
        """Hand frames that arrived (waiting at most ``timeout_s`` for the first; events
        without frames, such as a page connecting, do not end the wait), oldest first, each
        accepted by the validator; rejections are counted there."""
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            self._arrived.clear()  # before draining: an event pushed meanwhile sets it again
            frames = self._drain()
            remaining = deadline - time.monotonic()
            if frames or remaining <= 0:
                return frames
            self._arrived.wait(remaining)

    def _drain(self) -> list[HandFrame]:
        frames: list[HandFrame] = []
        while True:
            try:
                kind, payload = self._events.popleft()
            except IndexError:
                return frames
            if kind == "frames":
                for frame in payload:
                    reason = None if self.validator is None else self.validator.check(frame)
                    if reason is None:
                        frames.append(frame)
                    else:
                        self.refused[reason] += 1
            elif kind == "reject":
                if self.validator is not None:
                    self.validator.reject(*payload)
            elif kind == "driver" and self.validator is not None:
                self.validator.reset()  # a new page: its clock starts the order over

    # ------------------------------------------------------------------ server thread
    def _run(self, ssl_context) -> None:
        try:
            asyncio.run(self._main(ssl_context))
        except BaseException as exc:  # pragma: no cover - reported to the constructor
            self._error = self._error or exc
            self._ready.set()
            log.exception("the WebXR server stopped")

    async def _main(self, ssl_context) -> None:
        from websockets.asyncio.server import serve

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        try:
            server = await serve(
                self._handler,
                self.config.host,
                self.config.port,
                ssl=ssl_context,
                process_request=self._http,
                max_size=self.config.max_message_bytes,
                compression=None,
                server_header="beavr_sim",
                ping_interval=5,
                ping_timeout=10,
                close_timeout=1,
                logger=logging.getLogger("beavr_sim.headset.webxr_server.websockets"),
            )
        except OSError as exc:
            self._error = exc
            self._ready.set()
            return
        self.port = server.sockets[0].getsockname()[1]
        self._ready.set()
        async with server:
            await self._stop.wait()

    def _put(self, kind: str, payload: object) -> None:
        if len(self._events) >= MAX_PENDING_EVENTS:
            try:
                self._events.popleft()
                self.stats.dropped_events += 1
            except IndexError:
                pass
        self._events.append((kind, payload))
        self._arrived.set()

    def refused_connections(self) -> dict[str, int]:
        """WebSockets refused at the handshake (:data:`HANDSHAKE_REFUSALS`): reason -> count."""
        counts = dict(self.stats.rejected)  # a copy first: the server thread adds to it
        return {r: counts[r] for r in HANDSHAKE_REFUSALS if counts.get(r)}

    def _reject(self, reason: str, detail: str) -> None:
        self.stats.rejected[reason] += 1
        self._put("reject", (reason, f"webxr: {detail}"))

    def _http(self, connection, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        path = urlsplit(request.path).path
        if path == WS_PATH:
            origin = request.headers.get("Origin")
            if origin is not None and urlsplit(origin).netloc != request.headers.get("Host"):
                self.stats.rejected["cross_origin"] += 1
                return connection.respond(403, "cross-origin WebSocket refused\n")
            refused = self.config.token.check_path(request.path)
            if refused is not None:
                self.stats.rejected[refused] += 1
                status = 401 if refused == NO_TOKEN else 403
                return connection.respond(status, f"WebSocket refused: {refused}\n")
            return None  # the WebSocket handshake goes on
        name = "index.html" if path == "/" else path.lstrip("/")
        found = self._files.get(name)
        if found is None:
            return connection.respond(404, "not found\n")
        body, content_type = found
        host = request.headers.get("Host", "")
        policy = (
            "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
            f"connect-src 'self' ws://{host} wss://{host}; img-src 'self' data:"
        )
        headers = Headers(
            [
                ("Content-Type", content_type),
                ("Content-Length", str(len(body))),
                ("Cache-Control", "no-store"),
                ("Content-Security-Policy", policy),
                ("X-Content-Type-Options", "nosniff"),
                ("Connection", "close"),
            ]
        )
        return Response(200, "OK", headers, body)

    async def _handler(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        self._connections.add(ws)
        self.stats.connections += 1
        try:
            await ws.send(encode_page_message(self._welcome))
            for kind in ("scene", "twin"):
                if kind in self._latest:
                    await ws.send(self._latest[kind])
            async for message in ws:
                self._on_message(ws, message)
        except ConnectionClosed:
            pass
        finally:
            self._connections.discard(ws)
            if self._driver is ws:
                self._driver = None
                log.info("the WebXR page that drove the robot closed")

    def _on_message(self, ws, message: str | bytes) -> None:
        t_receive = self._clock()
        self.stats.messages += 1
        try:
            parsed = parse_message(message)
            if isinstance(parsed, HandsMessage):
                if self._driver is None:
                    self._driver = ws
                    self._put("driver", None)
                elif self._driver is not ws:
                    self._reject("second_page", "another page is driving; close it first")
                    return
                frames = hand_frames(parsed, t_receive)
                self.stats.hand_messages += 1
                self.stats.hand_times.append(t_receive)
                self._put("frames", frames)
            elif isinstance(parsed, HelloMsg):
                self.stats.agent = parsed.agent[:200]
                log.info("WebXR page connected: %s", self.stats.agent)
            elif isinstance(parsed, SessionMsg):
                self.stats.sessions_started += parsed.state == "started"
                log.info("WebXR page: XR session %s (%s)", parsed.state, parsed.mode[:40])
        except WebXRProtocolError as err:
            self._reject(err.reason, str(err))
        except Exception as exc:  # never let a message end the connection or the server
            self._reject("internal_error", repr(exc))

    def _send_all(self, kind: str, message: dict) -> None:
        from websockets.asyncio.server import broadcast

        text = encode_page_message(message)
        self._latest[kind] = text
        ready = []
        for ws in self._connections:
            transport = getattr(ws, "transport", None)
            buffered = transport.get_write_buffer_size() if transport is not None else 0
            if buffered > self.config.max_buffered_bytes:
                self.stats.twin_skipped += 1
            else:
                ready.append(ws)
        if ready:
            broadcast(ready, text)
            self.stats.twin_sent += len(ready)
