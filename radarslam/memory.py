"""Handing the heap's free memory back to the system during long runs.

A SLAM run keeps every key frame's cloud for the whole run, allocated between short-lived
buffers (images for the place-recognition network, registrations, graph updates). glibc's
allocator keeps the pages between the long-lived blocks once the short-lived ones are freed, so
the process grows faster than what it holds: on the 32-scene city subset it ended at 1.15 GB
where the key frames and the loaded libraries need about 0.6 GB. ``malloc_trim`` returns those
pages; it changes no result.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, or None where the C library has none (macOS, musl, Windows)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Give the heap's free pages back to the system; False where the C library cannot."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
