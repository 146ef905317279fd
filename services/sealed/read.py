"""Reading a sealed run: where it is (warm, or cold once restored), and its chunk index.

A cold run not restored is a CONFLICT saying how to restore it; a deleted one is GONE."""

from __future__ import annotations

import datetime as dt
import threading
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import cached_property

from cachetools import LRUCache
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.models import Run, RunLifecycle
from core.clock import aware
from core.errors import ConflictError, GoneError
from core.states import RestoreState, Tier
from services.rrd.chunk_index import IndexRows
from services.sealed.index import IndexTable, read_index
from services.sealed.tiers import readable_when_cold
from services.sealed.write import INDEX, RECORDING
from services.storage.objectstore import ObjectStore
from services.storage.readahead import read_soon

# Chunk indexes read lately, kept by how many rows they hold (as columns, a few hundred bytes a row;
# a few KB once every row is made): a run's windows asked one after another (a viewer, a dataset
# export) read its index once. A run of 5 GB has about 3,000 rows.
CACHED_INDEX_ROWS = 30_000
_indexes: LRUCache[tuple[str, str, int, str], IndexTable] = LRUCache(CACHED_INDEX_ROWS, getsizeof=len)
_indexes_lock = threading.Lock()


@dataclass(frozen=True)
class SealedRecording:
    """A sealed run's recording in a store. Its chunk index (`index`, every row: `rows`) is read on
    first use: a whole download needs none of it, and a run of many GB has tens of thousands of
    rows, of which a window makes only those it needs."""

    store: ObjectStore
    prefix: str
    size: int  # of recording.rrd
    version: str = ""  # what tells this recording from one sealed again under the prefix (etag, time)
    index_read: Future[bytes] | None = field(default=None, compare=False)  # its bytes, asked for already

    @cached_property
    def index(self) -> IndexTable:
        key = (self.store.url, self.prefix, self.size, self.version)
        with _indexes_lock:
            found = _indexes.get(key) if self.version else None
        if found is None:
            data = self.index_read.result() if self.index_read is not None else None
            found = read_index(data if data is not None else self.store.get_range(f"{self.prefix}/{INDEX}"))
            if self.version and len(found) <= CACHED_INDEX_ROWS:
                with _indexes_lock:
                    _indexes[key] = found
        return found

    @property
    def rows(self) -> IndexRows:
        return self.index.all()

    @property
    def key(self) -> str:
        return f"{self.prefix}/{RECORDING}"

    def timeline_types(self) -> dict[str, str]:
        index = self.index
        types: dict[str, str] | None = index.derived.get("timeline_types")
        if types is None:
            types = index.derived["timeline_types"] = index.timeline_types()
        return dict(types)


def _when(value: dt.datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M UTC") if value is not None else "an unknown time"


def locate_sealed(
    catalog: sessionmaker[Session], warm: ObjectStore, run_id: str, now: dt.datetime, *, index: bool = False
) -> SealedRecording:
    """Where a run that left the hot tier can be read: the warm store (cold runs once restored).
    A cold run not restored is a CONFLICT saying how to restore it; a deleted one is GONE. The
    recording's size is the store's (a HEAD): a sealing of late data that failed half-way leaves a
    new recording beside the catalog's old figures, and a store that cannot be reached is an error
    before any answer has started. `index`: its chunk index will be needed (a window), so unless
    one of the run's is cached it is read while the HEAD is under way, not after it."""
    return open_sealed(warm, sealed_prefix(catalog, run_id, now), index=index)


def sealed_prefix(catalog: sessionmaker[Session], run_id: str, now: dt.datetime) -> str:
    """The prefix of a sealed run's objects in the warm store, checked as `locate_sealed` checks it,
    for readers that need its recording but not its chunk index."""
    with session_scope(catalog) as session:
        found = queries.run_and_lifecycle(session, run_id)
        if found is None:
            raise queries.run_not_found(run_id)
        return readable_prefix(*found, now)


def readable_prefix(run: Run, life: RunLifecycle, now: dt.datetime) -> str:
    """The warm prefix of a sealed run that can be read now; CONFLICT for a cold run not restored
    (saying how to restore it), GONE for a deleted one."""
    run_id = run.id
    if run.tier == Tier.DELETED:
        raise GoneError(
            f"run {run_id!r} was deleted on {_when(life.deleted_at)} by {life.deleted_by}"
            + (f" (retention policy {life.deleted_policy!r})" if life.deleted_policy else "")
        )
    restored = readable_when_cold(life.archive_mode) or (
        life.restore_state == RestoreState.RESTORED and (life.restore_until is None or aware(life.restore_until) > now)
    )
    if run.tier == Tier.COLD and not restored:
        doing = (
            f"a restore was asked for at {_when(life.restore_requested_at)} and is under way: try again later"
            if life.restore_state == RestoreState.RESTORING
            else f"restore it with POST /v1/runs/{run_id}/restore or `fleet runs restore {run_id}`"
        )
        raise ConflictError(f"run {run_id!r} is archived in the cold tier since {_when(life.archived_at)}; {doing}")
    return life.prefix


def open_sealed(store: ObjectStore, prefix: str, *, index: bool = False) -> SealedRecording:
    index_read = read_soon(store.get_range, f"{prefix}/{INDEX}") if index and not _cached(store, prefix) else None
    info = store.head(f"{prefix}/{RECORDING}")
    version = f"{info.etag or ''}@{info.last_modified.isoformat()}"
    return SealedRecording(store, prefix, info.size, version, index_read)


def _cached(store: ObjectStore, prefix: str) -> bool:
    """Whether an index of the prefix's recording is cached (of which version, the HEAD says)."""
    with _indexes_lock:
        return any(url == store.url and at == prefix for url, at, _, _ in _indexes)
