"""Keep freed memory for the next allocation of the same size (glibc's allocator).

A calibration allocates and frees the same large arrays over and over: each message's bytes
while the bag is read, each evaluation's Jacobians, each round's maps. glibc serves a block above
its mmap threshold with a fresh mapping and returns it to the system when it is freed, and it
trims the heap's free top; the next array of that size then pays a page fault for every 4 kB it
touches. On the 2-core benchmark host that is 0.4-0.5 GB/s, so reading a 300 MB OS1-64 bag
spent more time in page faults than in reading.

:func:`keep_freed_memory` raises the mmap threshold to glibc's largest (32 MB: larger blocks are
rare and still mapped fresh) and keeps up to 1 GB of freed heap instead of trimming it: the
peak memory of a run is unchanged, the memory stays with the process until it ends. It is
called by the command line at start, before the heavy work (the forked stages inherit it).
Elsewhere (not glibc, or ``mallopt`` refused) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

__all__ = ["keep_freed_memory"]

logger = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 1024 * 1024
"""Blocks above this are mapped fresh (glibc's largest threshold on 64-bit systems)."""

TRIM_THRESHOLD = 1024 * 1024 * 1024
"""Freed memory at the heap's top kept for reuse before it is returned, bytes."""

TOP_PAD = 64 * 1024 * 1024
"""Extra memory asked for each time the heap grows, bytes."""


def keep_freed_memory() -> bool:
    """Tune glibc's allocator to reuse freed blocks (see the module docstring).

    Returns:
        Whether every setting was accepted (False off glibc).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    settings = (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
        (_M_TOP_PAD, TOP_PAD),
    )
    accepted = all(mallopt(param, value) == 1 for param, value in settings)
    if not accepted:
        logger.debug("The allocator did not accept every setting; it keeps its defaults.")
    return accepted
