"""Process-level tuning for the long-running service."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import sys

log = logging.getLogger(__name__)

# glibc mallopt parameters
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def tune_allocator() -> bool:
    """Keep freed memory for reuse instead of returning it to the kernel after every large message.

    Chunks of a few MB pass through several buffers (gRPC, the hot-tier write, the LZ4 output read
    for indexing); with glibc's defaults each lands on freshly mapped pages, and the page faults
    cost more than the copies. Memory stays bounded: at most the trim threshold is kept unused."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = bool(libc.mallopt(_M_MMAP_THRESHOLD, 64 * 1024 * 1024) == 1)
        ok = bool(libc.mallopt(_M_TRIM_THRESHOLD, 256 * 1024 * 1024) == 1) and ok
    except (OSError, AttributeError):
        return False
    if not ok:
        log.info("allocator tuning not applied")
    return ok


def freeze_startup_objects() -> int:
    """Leave the objects made at start-up (modules, the app, its caches: some 100,000, as long-lived
    as the process) out of every later garbage collection; returns how many. A full collection then
    walks only what the service made since, instead of all of them again every few thousand chunks."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
