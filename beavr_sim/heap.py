"""The process's C heap (glibc malloc): how much of it is in use.

A long session allocates and frees the same sizes for hours from several threads (the twin,
the mirror's writers, the SDKs' receivers); glibc keeps freed memory in its arenas, so the
resident memory can creep up while the memory in use stays flat. :func:`in_use_mb` tells the
two apart (the soak benchmark fits both). None with another C library.
"""

from __future__ import annotations

import ctypes


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd",
            "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
        )
    ]  # fmt: skip


def _libc_function(name: str, restype):
    try:
        fn = getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError):
        return None
    fn.restype = restype
    return fn


_MALLINFO2 = _libc_function("mallinfo2", _MallInfo2)  # glibc 2.33 and later


def in_use_mb() -> float | None:
    """MB the C allocator has handed out and not had back (every arena and the mmapped
    blocks: ``mallinfo2``); None where that is not available."""
    if _MALLINFO2 is None:
        return None
    info = _MALLINFO2()
    return (info.uordblks + info.hblkhd) / (1024.0 * 1024.0)


def free_mb() -> float | None:
    """MB glibc holds in its arenas free (``mallinfo2().fordblks``: freed chunks not yet given
    back to the system); None where that is not available."""
    if _MALLINFO2 is None:
        return None
    return _MALLINFO2().fordblks / (1024.0 * 1024.0)
