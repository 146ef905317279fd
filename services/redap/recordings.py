"""A segment's recording as the catalog server reads it: the hot file of a run this node is writing,
else the sealed `recording.rrd` in the warm store (a cold run once restored), opened as the
`IndexedRecording` downloads read too: by byte range, with its chunk index to find a chunk by id."""

from __future__ import annotations

import threading
import weakref

from cachetools import TTLCache

from catalog import queries
from catalog.db import session_scope
from core.errors import NotFoundError, UnavailableError
from core.states import Tier
from services.redap.depot import Depot
from services.runs.indexed import IndexedRecording, open_hot, open_sealed_object
from services.sealed.index import from_parquet
from services.sealed.read import sealed_prefix
from services.sealed.write import INDEX, RECORDING
from services.storage.objectstore import ObjectNotFoundError, ObjectStore

LOCATION_TTL_S = 10.0
LOCATIONS_KEPT = 4096


def open_recording(depot: Depot, run_id: str, *, cached: bool = False) -> IndexedRecording:
    """The run's hot file if this node writes it, else its sealed recording. NOT_FOUND for an
    unknown run, FAILED_PRECONDITION naming `fleet runs restore` for a cold run not restored.

    `cached`: a sealed run found in the last `LOCATION_TTL_S` is not looked up in the catalog again
    (a viewer opening a run asks for its chunks in many calls) if its recording is still there with
    the same size (deleted or sealed again: the catalog is asked). A run archived in that time may
    be read from its warm copy until then."""
    hot = depot.hot.hot_recording(run_id) if depot.hot is not None else None
    if hot is not None:
        try:
            return open_hot(hot)
        except FileNotFoundError:
            pass  # sealed and removed since it was asked for: read it where it went
    found = _LOCATIONS.get(depot.catalog, run_id) if cached else None
    if found is not None:
        prefix, size = found
        try:
            recording = _sealed(depot.warm, prefix)
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
    recording = _sealed(depot.warm, prefix)
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


def _sealed(store: ObjectStore, prefix: str) -> IndexedRecording:
    key = f"{prefix}/{RECORDING}"
    return open_sealed_object(
        store, key, store.head(key).size, lambda: from_parquet(store.get_range(f"{prefix}/{INDEX}"))
    )
