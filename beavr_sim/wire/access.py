"""Who may drive the robot: the session token of the WebXR page (and the browser view).

A :class:`SessionToken` is made fresh for every session (``secrets.token_urlsafe``) or given
with ``--token``. It is compared in constant time (``hmac.compare_digest``). The loopback rule:
on 127.0.0.1 / ::1 / localhost the token is off by default (only this machine can connect); on
any other address it is on; ``--token T`` forces it on everywhere.
"""

from __future__ import annotations

import hmac
import ipaddress
import secrets
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

#: Why a handshake was refused, as counted in ``rejected_by_reason``.
NO_TOKEN = "no_token"
BAD_TOKEN = "bad_token"
TOKEN_QUERY = "token"


def is_loopback(host: str) -> bool:
    """``host`` (a name or an address) is this machine only: localhost, 127.0.0.0/8, ::1."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def new_token_value() -> str:
    """A fresh random token (URL-safe, 32 characters)."""
    return secrets.token_urlsafe(24)


@dataclass(frozen=True)
class SessionToken:
    """The token clients must present; ``required`` False means every client is let in."""

    value: str
    required: bool

    def __post_init__(self) -> None:
        if not isinstance(self.value, str) or not self.value or not self.value.isprintable():
            raise ValueError("session token must be a non-empty printable string")
        if any(c in self.value for c in " &?#/%"):
            raise ValueError("session token may not contain spaces or any of '&?#/%'")

    @classmethod
    def for_host(
        cls, host: str, given: str | None = None, *, value: str | None = None
    ) -> SessionToken:
        """Token for a server bound to ``host``: ``given`` (``--token``) forces it on; else it
        is on off loopback, with ``value`` (one per session) or a fresh one."""
        if given is not None:
            return cls(given, True)
        return cls(value or new_token_value(), not is_loopback(host))

    def check(self, presented: str | None) -> str | None:
        """``None`` when ``presented`` is acceptable, else the refusal reason."""
        if not self.required:
            return None
        if not presented:
            return NO_TOKEN
        if not hmac.compare_digest(presented.encode(), self.value.encode()):
            return BAD_TOKEN
        return None

    def check_path(self, path: str) -> str | None:
        """:meth:`check` on the ``?token=`` of a request path."""
        values = parse_qs(urlsplit(path).query).get(TOKEN_QUERY, [])
        return self.check(values[0] if values else None)

    def url_suffix(self) -> str:
        """``?token=...`` to append to a printed URL (empty when the token is off)."""
        return f"?{TOKEN_QUERY}={self.value}" if self.required else ""

    def describe(self) -> str:
        """One line for the terminal: whether and why a token is needed."""
        if self.required:
            return "access: a session token is required (it is in the URL above)"
        return "access: no token on a loopback address (only this machine can connect); --token T turns it on"
