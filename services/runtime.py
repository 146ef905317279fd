"""Process-level tuning for the long-running service."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import pyarrow as pa

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
        return False
    # Arrow's buffers from the same tuned allocator. With Arrow's own (mimalloc), a sealed run's
    # chunk index of 29,000 rows took 60-130 ms of CPU to parse on a server's first windows and
    # 20 ms on later ones; on glibc kept warm as above, 18-22 ms from the first (a window's first
    # byte after a restart 126-229 -> 94-104 ms).
    pa.set_memory_pool(pa.system_memory_pool())
    return True


def freeze_startup_objects() -> int:
    """Leave the objects made at start-up (modules, the app, its caches: some 100,000, as long-lived
    as the process) out of every later garbage collection; returns how many. A full collection then
    walks only what the service made since, instead of all of them again every few thousand chunks."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


@contextmanager
def collection_paused() -> Iterator[None]:
    """No garbage collection while the block makes many small objects that hold no cycles (a big
    run's parsed chunk index: tens of thousands of rows of tuples): the collections their count
    sets off would walk everything the service made since it started, each time, and free nothing.
    Collection resumes after; a block inside another's leaves it to the outer one to resume."""
    paused = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if paused:
            gc.enable()


REALTIME = (getattr(os, "SCHED_FIFO", -1), getattr(os, "SCHED_RR", -1))


def process_threads() -> set[int]:
    """The ids of this process's threads (none where /proc does not list them)."""
    try:
        return {int(tid) for tid in os.listdir("/proc/self/task")}
    except OSError:
        return set()


def drop_realtime(threads: Iterable[int]) -> list[int]:
    """Put each of `threads` (this process's) that runs under real-time scheduling back to
    SCHED_OTHER; the ones moved. A library may ask for real-time priority for its threads (SVT-AV1
    run as root asks SCHED_FIFO 99): one busy thread at that priority starves the whole machine,
    and every process the thread starts after inherits it."""
    if not hasattr(os, "sched_getscheduler"):
        return []
    moved = []
    for tid in threads:
        try:
            if os.sched_getscheduler(tid) in REALTIME:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
                moved.append(tid)
        except OSError:  # the thread ended
            continue
    return moved
