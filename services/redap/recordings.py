"""A segment's recording as the catalog server reads it: the hot file of a run this node is writing,
else the sealed `recording.rrd` in the warm store (a cold run once restored), read by byte range,
with its chunk index to find a chunk by id."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field

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
from services.storage.objectstore import ObjectStore


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


def open_recording(depot: Depot, run_id: str) -> RunRecording:
    """The run's hot file if this node writes it, else its sealed recording. NOT_FOUND for an
    unknown run, FAILED_PRECONDITION naming `fleet runs restore` for a cold run not restored."""
    hot = depot.hot.hot_recording(run_id) if depot.hot is not None else None
    if hot is not None:
        try:
            return _hot(run_id, hot)
        except FileNotFoundError:
            pass  # sealed and removed since it was asked for: read it where it went
    if depot.warm is None:
        raise UnavailableError(f"run {run_id!r} is not hot on this node, and this node reads no sealed runs")
    try:
        prefix = sealed_prefix(depot.catalog, run_id, depot.clock())
    except NotFoundError:
        _not_sealed_yet(depot, run_id)
        raise
    return _sealed(run_id, depot.warm, prefix)


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
