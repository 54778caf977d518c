"""Network configuration of the teleop pipeline: the one place port numbers live.

Two groups of sockets:

- **headset** sockets speak the BEAVR Quest app's protocol (see ``docs/formats.md``): the PC
  binds PULL for the app's keypoint, resolution and pause streams and binds PUB for the images
  the headset shows. They bind on :attr:`TransportConfig.headset_host` (loopback by default;
  a LAN address such as ``"0.0.0.0"`` only when the user asks for it).
- **pipeline** streams carry typed messages (:mod:`beavr_sim.wire.messages`) between the
  operator and twin processes on :attr:`TransportConfig.host`.

The WebXR page's server (``--source webxr``: HTTP(S) and one WebSocket, not ZeroMQ) takes its
default port from :attr:`PortConfig.webxr`; its host is its own option (``--webxr-host``).
"""

from __future__ import annotations

import ipaddress
import re
import socket
from contextlib import ExitStack
from dataclasses import dataclass, field, fields

from beavr_sim.naming import check_name

#: Port names that belong to the headset (Quest app) side.
HEADSET_PORTS = (
    "quest_right",
    "quest_left",
    "quest_resolution",
    "quest_pause",
    "headset_camera",
    "headset_graph",
)


@dataclass(frozen=True)
class PortConfig:
    """TCP port of every stream.

    Headset ports are fixed by the Quest app's ``Network.json``; change them only together
    with the app. Pipeline ports are ours (a block from 5572).
    """

    # Headset -> PC (the app connects PUSH, the PC binds PULL).
    quest_right: int = 8087
    quest_left: int = 8110
    quest_resolution: int = 8095
    quest_pause: int = 8100
    # PC -> headset (the PC binds PUB, the app connects SUB).
    headset_camera: int = 10505
    headset_graph: int = 15001
    # The WebXR page and its WebSocket (beavr_sim.headset.webxr_server; HTTPS off loopback).
    webxr: int = 8443
    # Pipeline streams (msgpack messages, PUB/SUB).
    commands: int = 5572
    robot_state: int = 5573
    session: int = 5574

    def __post_init__(self) -> None:
        seen: dict[int, str] = {}
        for f in fields(self):
            port = getattr(self, f.name)
            if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
                raise ValueError(f"port {f.name} must be an integer in 1..65535, got {port!r}")
            if port in seen:
                raise ValueError(
                    f"ports {seen[port]} and {f.name} are both {port}; ports must differ"
                )
            seen[port] = f.name

    @classmethod
    def free(cls, host: str = "127.0.0.1") -> PortConfig:
        """Every stream on a currently free port of ``host`` (tests, parallel runs)."""
        names = [f.name for f in fields(cls)]
        return cls(**dict(zip(names, free_tcp_ports(len(names), host), strict=True)))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in fields(self))

    def port(self, name: str) -> int:
        """Port of the stream ``name``; raises with the valid names."""
        return getattr(self, check_name("port", name, self.names))


def free_tcp_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """``n`` distinct TCP ports that are free on ``host`` right now (the OS picks them).

    They are released before returning, so another process could take one first: fine for
    tests, not a reservation.
    """
    with ExitStack() as stack:
        ports = []
        for _ in range(n):
            sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
            sock.bind((host, 0))
            ports.append(sock.getsockname()[1])
    return ports


_HOST_NAME = re.compile(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?")


def _check_host(kind: str, host: object) -> None:
    """IPv4 address, or a host / interface name (IPv6 would need the ZMQ IPV6 option)."""
    if host == "*":
        raise ValueError(f"{kind}: use '0.0.0.0' to listen on every interface, not '*'")
    if not isinstance(host, str) or not _HOST_NAME.fullmatch(host):
        raise ValueError(
            f"{kind} must be an IPv4 address or a host name (e.g. '127.0.0.1', '0.0.0.0'), "
            f"got {host!r}"
        )
    if host.replace(".", "").isdigit():
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            raise ValueError(f"{kind} {host!r} is not a valid IPv4 address") from None


@dataclass(frozen=True)
class TransportConfig:
    """Where every socket binds or connects.

    ``host``: address of the pipeline streams (loopback: one machine). ``headset_host``:
    interface the headset sockets bind to; loopback by default so nothing is exposed to the
    network unless the user passes a LAN address (``"0.0.0.0"`` = every interface).
    """

    host: str = "127.0.0.1"
    headset_host: str = "127.0.0.1"
    ports: PortConfig = field(default_factory=PortConfig)
    #: IP addresses the Quest app's sockets accept peers from (``--headset-allow``, checked by
    #: ``headset.address_gate``); None: any host.
    headset_allow: frozenset[str] | None = None

    def __post_init__(self) -> None:
        _check_host("host", self.host)
        _check_host("headset_host", self.headset_host)
        if not isinstance(self.ports, PortConfig):
            raise ValueError(f"ports must be a PortConfig, got {type(self.ports).__name__}")

    def endpoint(self, name: str, bind: bool) -> str:
        """ZMQ tcp endpoint of stream ``name``, for binding or for connecting.

        Headset streams use ``headset_host``, pipeline streams ``host``. A connect endpoint for
        a socket bound on ``0.0.0.0`` goes to loopback (the only address known to be local).
        """
        port = self.ports.port(name)
        host = self.headset_host if name in HEADSET_PORTS else self.host
        if not bind and host == "0.0.0.0":
            host = "127.0.0.1"
        return f"tcp://{host}:{port}"
