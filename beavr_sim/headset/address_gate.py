"""Address gate for the Quest app's sockets: a ZeroMQ ZAP handler allowing listed peers only.

The Quest app cannot send a token, so the headset's IP address is the credential
(``--headset-allow IP[,IP]``). :class:`AddressGate` answers ZAP requests on
``inproc://zeromq.zap.01`` of one context from its own thread: a peer whose address is in
``allowed`` is accepted, any other is denied at the handshake (its messages never arrive) and
counted in :attr:`AddressGate.refused` as ``not_allowed``. Only sockets with a ZAP domain
(:meth:`AddressGate.guard`) are checked. One gate per context (ZeroMQ allows one handler).
"""

from __future__ import annotations

import ipaddress
import threading
from collections import Counter

import zmq

ZAP_ENDPOINT = "inproc://zeromq.zap.01"
ZAP_DOMAIN = b"beavr-headset"
NOT_ALLOWED = "not_allowed"


def parse_allow_list(text: str) -> frozenset[str] | None:
    """``--headset-allow``: ``"any"`` -> None (every host), else comma-separated IP addresses."""
    if text.strip() == "any":
        return None
    allowed = set()
    for item in (part.strip() for part in text.split(",")):
        try:
            allowed.add(str(ipaddress.ip_address(item)))
        except ValueError:
            raise ValueError(
                f"--headset-allow: {item!r} is not an IP address (give IP[,IP] or 'any')"
            ) from None
    return frozenset(allowed)


class AddressGate:
    """Accepts ZAP-checked connections from ``allowed`` addresses only (a thread; :meth:`close`)."""

    def __init__(self, context: zmq.Context, allowed: frozenset[str]):
        self.allowed = frozenset(allowed)
        self.refused: Counter[str] = Counter()
        self.accepted = 0
        self._socket = context.socket(zmq.REP)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.bind(ZAP_ENDPOINT)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="zap-gate", daemon=True)
        self._thread.start()

    def guard(self, socket: zmq.Socket) -> None:
        """Have ``socket`` (before it binds) checked by this gate."""
        socket.setsockopt(zmq.ZAP_DOMAIN, ZAP_DOMAIN)

    def _run(self) -> None:
        poller = zmq.Poller()
        poller.register(self._socket, zmq.POLLIN)
        while not self._stop.is_set():
            if not poller.poll(100):
                continue
            try:
                frames = self._socket.recv_multipart()
            except zmq.ZMQError:
                return
            version, request_id, _domain, address = frames[:4]
            ok = address.decode(errors="replace") in self.allowed
            if ok:
                self.accepted += 1
            else:
                self.refused[NOT_ALLOWED] += 1
            status = (b"200", b"OK") if ok else (b"400", b"address not allowed")
            self._socket.send_multipart([version, request_id, *status, b"", b""])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._socket.close(linger=0)
