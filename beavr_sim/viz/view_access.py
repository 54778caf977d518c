"""Which browser-view clients may press which controls (the session token on the view).

Anyone who can see the view may stop the robot (``estop``, ``pause``). Controls that move it,
release an e-stop, reset or record (:data:`GUARDED`) act only for a client that entered the
session token; a refused press is counted in :attr:`ViewAccess.refused` by action. When the
token is not required (loopback) every client may press everything.
"""

from __future__ import annotations

from collections import Counter

from beavr_sim.naming import check_name
from beavr_sim.wire.access import SessionToken

#: Controls anyone may press: they only stop motion.
SAFE = ("estop", "pause")
#: Controls that need the token.
GUARDED = ("resume", "reset", "record", "discard", "release")
ACTIONS = SAFE + GUARDED


class ViewAccess:
    """Per-client permissions of the browser view (clients are viser client ids)."""

    def __init__(self, token: SessionToken):
        self.token = token
        self._granted: set[int] = set()
        self.refused: Counter[str] = Counter()

    def enter(self, client_id: int, presented: str) -> bool:
        """A client typed a token: grants it the guarded controls when it is right."""
        ok = self.token.check(presented) is None
        if ok:
            self._granted.add(client_id)
        else:
            self._granted.discard(client_id)
        return ok

    def forget(self, client_id: int) -> None:
        self._granted.discard(client_id)

    def permits(self, action: str, client_id: int | None) -> bool:
        """Whether ``client_id`` may press ``action``; a refusal is counted."""
        check_name("view action", action, ACTIONS)
        if action in SAFE or not self.token.required or client_id in self._granted:
            return True
        self.refused[action] += 1
        return False
