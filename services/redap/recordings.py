"""A segment's recording as the catalog server reads it: the hot file of a run this node is writing,
else the sealed `recording.rrd` in the warm store (a cold run once restored), read by byte range,
with its chunk index to find a chunk by id."""

from __future__ import annotations

import os
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field

from cachetools import TTLCache

from catalog import queries
from catalog.db import session_scope
from core.errors import NotFoundError, UnavailableError
from core.states import Tier
from services.hot.read import HotRecording
from services.redap.depot import Depot
from services.rrd.chunk_index import CHUNK, IndexRow
from services.sealed.index import from_parquet
from services.sealed.read import sealed_prefix
from services.sealed.write import INDEX, RECORDING
from services.storage.objectstore import ObjectNotFoundError, ObjectStore

LOCATION_TTL_S = 10.0
LOCATIONS_KEPT = 4096


@dataclass
class RunRecording:
    """One run's recording: `size` bytes, read by range; `rows()` its chunk index (read once)."""

    run_id: str
    size: int
    read: Callable[[int, int], bytes]  # (offset, length) -> at most `length` bytes
    load_rows: Callable[[], list[IndexRow]]
    hot: HotRecording | None = None
    store: ObjectStore | None = None
    key: str = ""  # of the sealed recording in `store`
    close: Callable[[], None] = field(default=lambda: None)
    _rows: list[IndexRow] | None = None
    _by_chunk: dict[bytes, IndexRow] | None = None

    def rows(self) -> list[IndexRow]:
        if self._rows is None:
            self._rows = self.load_rows()
        return self._rows

    def chunk_row(self, chunk_id: bytes) -> IndexRow | None:
        """Where the chunk with this id is in the recording (None: not in it)."""
        if self._by_chunk is None:
            self._by_chunk = {r.chunk_id: r for r in self.rows() if r.kind == CHUNK and r.chunk_id is not None}
        return self._by_chunk.get(chunk_id)


def open_recording(depot: Depot, run_id: str, *, cached: bool = False) -> RunRecording:
    """The run's hot file if this node writes it, else its sealed recording. NOT_FOUND for an
    unknown run, FAILED_PRECONDITION naming `fleet runs restore` for a cold run not restored.

    `cached`: a sealed run found in the last `LOCATION_TTL_S` is not looked up in the catalog again
    (a viewer opening a run asks for its chunks in many calls) if its recording is still there with
    the same size (deleted or sealed again: the catalog is asked). A run archived in that time may
    be read from its warm copy until then."""
    hot = depot.hot.hot_recording(run_id) if depot.hot is not None else None
    if hot is not None:
        try:
            return _hot(run_id, hot)
        except FileNotFoundError:
            pass  # sealed and removed since it was asked for: read it where it went
    if depot.warm is None:
        raise UnavailableError(f"run {run_id!r} is not hot on this node, and this node reads no sealed runs")
    found = _LOCATIONS.get(depot.catalog, run_id) if cached else None
    if found is not None:
        prefix, size = found
        try:
            recording = _sealed(run_id, depot.warm, prefix)
            if recording.size == size:  # the same object: not deleted, not sealed again meanwhile
                return recording
        except ObjectNotFoundError:
            pass
        _LOCATIONS.forget(depot.catalog, run_id)
    try:
        prefix = sealed_prefix(depot.catalog, run_id, depot.clock())
    except NotFoundError:
        _not_sealed_yet(depot, run_id)
        raise
    recording = _sealed(run_id, depot.warm, prefix)
    _LOCATIONS.put(depot.catalog, run_id, (prefix, recording.size))
    return recording


class _Locations:
    """Sealed runs found lately, per catalog: run id -> (prefix, size of its recording), each kept
    `LOCATION_TTL_S`, at most `LOCATIONS_KEPT` per catalog (the least recently used go first)."""

    def __init__(self) -> None:
        self._found: weakref.WeakKeyDictionary[object, TTLCache[str, tuple[str, int]]] = weakref.WeakKeyDictionary()
        self._lock = threading.Lock()

    def get(self, catalog: object, run_id: str) -> tuple[str, int] | None:
        with self._lock:
            runs = self._found.get(catalog)
            return runs.get(run_id) if runs is not None else None

    def put(self, catalog: object, run_id: str, where: tuple[str, int]) -> None:
        with self._lock:
            runs = self._found.get(catalog)
            if runs is None:
                runs = self._found[catalog] = TTLCache(LOCATIONS_KEPT, LOCATION_TTL_S)
            runs[run_id] = where

    def forget(self, catalog: object, run_id: str) -> None:
        with self._lock:
            runs = self._found.get(catalog)
            if runs is not None:
                runs.pop(run_id, None)


_LOCATIONS = _Locations()


def _not_sealed_yet(depot: Depot, run_id: str) -> None:
    """A run the catalog holds as hot that this node does not write: another node's, or one being
    sealed right now (UNAVAILABLE: try again)."""
    with session_scope(depot.catalog) as session:
        run = queries.get_run(session, run_id)
        tier = run.tier if run is not None else None
    if tier == Tier.HOT:
        raise UnavailableError(
            f"run {run_id!r} is hot on another node or being sealed right now: try again in a moment"
        )


def _hot(run_id: str, hot: HotRecording) -> RunRecording:
    fd = os.open(hot.path, os.O_RDONLY)  # kept open: a run sealed meanwhile stays readable

    def read(offset: int, length: int) -> bytes:
        return os.pread(fd, length, offset)

    return RunRecording(run_id, hot.size, read, lambda: hot.chunk_index().rows, hot=hot, close=lambda: os.close(fd))


def _sealed(run_id: str, store: ObjectStore, prefix: str) -> RunRecording:
    key = f"{prefix}/{RECORDING}"
    size = store.head(key).size

    def read(offset: int, length: int) -> bytes:
        return store.get_range(key, offset, length)

    def rows() -> list[IndexRow]:
        return from_parquet(store.get_range(f"{prefix}/{INDEX}"))

    return RunRecording(run_id, size, read, rows, store=store, key=key)
