"""What the session prints for the user to connect: URLs with the session token and a QR code.

Everything goes to stderr (stdout stays the JSON summary). A QR code of the WebXR URL (with its
token) is drawn in the terminal when the token is required, so a headset can open it by
looking at the screen instead of typing it.
"""

from __future__ import annotations

import sys
from typing import TextIO

from beavr_sim.wire.access import SessionToken


def announce_webxr(url: str, token: SessionToken, out: TextIO | None = None) -> None:
    """The WebXR page's URL (``?token=`` included), its access line and, with a token, a QR code."""
    out = out or sys.stderr
    print(f"WebXR page (open it in the headset's browser): {url}", file=out)
    print(token.describe(), file=out)
    if token.required:
        import segno  # local: only a networked session draws one

        segno.make(url, error="m").terminal(out=out, compact=True)
    out.flush()


def announce_view(url: str, token: SessionToken, out: TextIO | None = None) -> None:
    """The browser view's URL and, when its controls need it, the token to enter there."""
    out = out or sys.stderr
    print(f"browser view: {url}", file=out)
    if token.required:
        print(
            f"browser view: enter the session token {token.value} in its Access panel to "
            "resume, reset or record (anyone may press E-STOP)",
            file=out,
        )
    out.flush()
