"""How the mirror words a device failure: one line, with the traceback only under DEBUG.

Contract: :func:`one_line` never raises and keeps a driver's own message (it names the device
and what to check); :func:`log_error` logs on the mirror's logger.
"""

from __future__ import annotations

import logging

from beavr_sim.hardware.device import DeviceError

#: The mirror's one logger (every module of the package logs here).
log = logging.getLogger("beavr_sim.hardware.mirror")


def one_line(exc: BaseException) -> str:
    """An error as one line (a driver's message names the device and what to check)."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, DeviceError) else f"{type(exc).__name__}: {text}"


def log_error(message: str, *args) -> None:
    """One line; the traceback only with DEBUG logging on."""
    log.error(message, *args, exc_info=log.isEnabledFor(logging.DEBUG))
