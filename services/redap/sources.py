"""A dataset's runs as a query reads them: where each run's chunks are (this node's hot file, or the
sealed `recording.rrd` in the warm store), its chunk index rows, and its Sorbet schema. A segment
(`SegmentSource`) is a run, or of a run the chunks a snapshot's episode reads.

A sealed run is read from its `chunks.parquet` and the footer of its `recording.rrd` (the schema,
and each chunk's size once decompressed), and kept in a bounded cache under the recording's digest:
a run sealed again with chunks that came later is a new recording, so a new entry. A hot run is
read from the chunk index kept beside its file, as the file stands (cached per size of the file)."""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import Dataset, Run, RunLifecycle, RunObject
from core.errors import ConflictError, FleetError, GoneError, InternalError, UnavailableError
from core.ids import possible_ids
from core.states import Tier
from services.hot.read import HotRecording
from services.redap.cache import WeightedLru
from services.redap.depot import Depot
from services.redap.schema import merge_schemas, narrowed, rerun_order
from services.rrd.footer import read_footer
from services.rrd.manifest import read_manifest, read_sorbet_schema, sorbet_schema
from services.rrd.pb import common_pb2, log_msg_pb2
from services.sealed.index import CHUNK, IndexRow, from_parquet
from services.sealed.read import readable_prefix
from services.sealed.write import INDEX, RECORDING
from services.storage.objectstore import ObjectFile, ObjectStore

log = logging.getLogger(__name__)

RECORDING_STORE = "recording"  # IndexRow.store_kind of a recording's chunks (not its blueprint's)
# What the cache holds of runs' chunk rows, over all runs (a few hundred bytes a row).
CACHED_ROWS = 400_000
CACHED_SCHEMAS = 20_000


@dataclass(frozen=True)
class IndexedRecordingSource:
    """Where one run of a dataset is read from, or why it cannot be now: the run's recording and
    chunk index, found but not opened (an `IndexedRecording` holds a hot run's file open). A query
    reads only the index and the schema, kept in a cache under what is found here."""

    run_id: str
    hot: HotRecording | None = None
    prefix: str | None = None  # of a sealed run in the warm store
    digest: str = ""  # sha256 of the sealed recording.rrd: what the cache knows it by
    size: int = 0  # of the sealed recording.rrd
    unreadable: FleetError | None = None  # a cold run not restored, a hot run on another node


@dataclass(frozen=True)
class RunChunks:
    """One run's recording chunks as their index rows, each chunk's size once decompressed (when
    known) and the run's Sorbet schema in Rerun's column order."""

    run_id: str
    rows: tuple[IndexRow, ...]
    uncompressed: Mapping[bytes, int] = field(default_factory=dict)
    schema: pa.Schema = field(default_factory=lambda: pa.schema([]))


_chunks: WeightedLru[RunChunks] = WeightedLru(CACHED_ROWS, lambda found: max(1, len(found.rows)))
_schemas: WeightedLru[pa.Schema] = WeightedLru(CACHED_SCHEMAS)


def clear_caches() -> None:
    _chunks.clear()
    _schemas.clear()


# --- which runs, and where ---------------------------------------------------------------------


@dataclass(frozen=True)
class SegmentSource:
    """A segment as a query reads it: a run (an application's segment), or of a run only the chunks
    a snapshot's episode reads (`chunk_ids`)."""

    segment_id: str
    source: IndexedRecordingSource
    chunk_ids: frozenset[bytes] | None = None

    def rows(self, found: RunChunks) -> tuple[IndexRow, ...]:
        """The segment's rows of its run's chunks."""
        if self.chunk_ids is None:
            return found.rows
        return tuple(r for r in found.rows if r.chunk_id in self.chunk_ids)


@dataclass(frozen=True)
class DatasetView:
    """A dataset as one query sees it: its timelines (from the catalog) and its segments' sources."""

    name: str
    timelines: frozenset[str]
    segments: list[SegmentSource]
    empty: bool  # the dataset holds no segment (any timeline may be named of it)


def dataset_sources(
    depot: Depot, session: Session, dataset: Dataset, now: dt.datetime, only: frozenset[str] | None = None
) -> list[IndexedRecordingSource]:
    """The dataset's runs that hold data (by run id; `only` those named), with where each can be read."""
    query = sa.select(Run).where(Run.application_id == dataset.name, Run.tier != Tier.DELETED)
    if only is not None:
        query = query.where(Run.id.in_(sorted(possible_ids(only))))
    return run_sources(depot, session, list(session.scalars(query.order_by(Run.id))), now)


def run_sources(depot: Depot, session: Session, runs: list[Run], now: dt.datetime) -> list[IndexedRecordingSource]:
    """Where each of `runs` can be read now, or why not."""
    ids = [run.id for run in runs]
    lives = {life.run_id: life for life in session.scalars(sa.select(RunLifecycle).where(RunLifecycle.run_id.in_(ids)))}
    recordings = {
        obj.run_id: obj
        for obj in session.scalars(sa.select(RunObject).where(RunObject.run_id.in_(ids), RunObject.name == RECORDING))
    }
    return [_source(depot, run, lives.get(run.id), recordings.get(run.id), now) for run in runs]


def _source(
    depot: Depot, run: Run, life: RunLifecycle | None, recording: RunObject | None, now: dt.datetime
) -> IndexedRecordingSource:
    hot = depot.hot.hot_recording(run.id) if depot.hot is not None else None
    if hot is not None:
        return IndexedRecordingSource(run.id, hot=hot)
    if life is None or recording is None:
        return IndexedRecordingSource(
            run.id,
            unreadable=UnavailableError(
                f"run {run.id!r} is being written on another node of the depot: query it once it is sealed"
            ),
        )
    try:
        prefix = readable_prefix(run, life, now)
    except (ConflictError, GoneError) as exc:
        return IndexedRecordingSource(run.id, unreadable=exc)
    return IndexedRecordingSource(run.id, prefix=prefix, digest=recording.sha256, size=recording.size)


# --- reading a run -----------------------------------------------------------------------------


def run_chunks(depot: Depot, source: IndexedRecordingSource) -> RunChunks:
    """The run's chunks (cached for sealed runs); the source's error if it cannot be read now."""
    if source.unreadable is not None:
        raise source.unreadable
    if source.hot is not None:
        hot = source.hot
        return _chunks.get_or_load(("hot", str(hot.path), hot.size), lambda: _read_hot(source.run_id, hot))
    store, prefix = _sealed(depot, source)
    found = _chunks.get_or_load(
        (store.url, prefix, source.digest), lambda: _read_sealed(store, prefix, source.run_id, source.size)
    )
    _schemas.put((store.url, prefix, source.digest), found.schema)
    return found


def segment_schema(depot: Depot, segment: SegmentSource) -> pa.Schema:
    """The segment's Sorbet schema: its run's, or for an episode the columns of the entities and
    timelines its chunks hold."""
    if segment.chunk_ids is None:
        return run_schema(depot, segment.source)
    found = run_chunks(depot, segment.source)
    rows = segment.rows(found)
    return narrowed(found.schema, {r.entity_path or "/" for r in rows}, {t.name for r in rows for t in r.timelines})


def run_schema(depot: Depot, source: IndexedRecordingSource) -> pa.Schema:
    """The run's Sorbet schema in Rerun's order: for a sealed run, from its footer alone."""
    if source.unreadable is not None:
        raise source.unreadable
    if source.hot is not None:
        return run_chunks(depot, source).schema
    store, prefix = _sealed(depot, source)
    return _schemas.get_or_load(
        (store.url, prefix, source.digest), lambda: _footer_schema(_footer(store, prefix, source.size))
    )


def _sealed(depot: Depot, source: IndexedRecordingSource) -> tuple[ObjectStore, str]:
    assert source.prefix is not None  # a sealed source has one
    return depot.warm, source.prefix


def _read_sealed(store: ObjectStore, prefix: str, run_id: str, size: int) -> RunChunks:
    index = from_parquet(store.get_range(f"{prefix}/{INDEX}"))
    rows = tuple(r for r in index if r.kind == CHUNK and r.store_kind == RECORDING_STORE)
    footer = _footer(store, prefix, size)
    uncompressed: dict[bytes, int] = {}
    for manifest in _recording_manifests(footer):
        table = read_manifest(manifest)
        ids = table.column("chunk_id").to_pylist()
        sizes = table.column("chunk_byte_size_uncompressed").to_pylist()
        uncompressed.update(zip(ids, sizes, strict=True))
    return RunChunks(run_id, rows, uncompressed, _footer_schema(footer))


def _recording_manifests(footer: log_msg_pb2.RrdFooter) -> list[log_msg_pb2.RrdManifest]:
    return [m for m in footer.manifests if m.store_id.kind == common_pb2.STORE_KIND_RECORDING]


def _footer_schema(footer: log_msg_pb2.RrdFooter) -> pa.Schema:
    return rerun_order(merge_schemas(read_sorbet_schema(m) for m in _recording_manifests(footer)))


def _footer(store: ObjectStore, prefix: str, size: int) -> log_msg_pb2.RrdFooter:
    footer = read_footer(ObjectFile(store, f"{prefix}/{RECORDING}", size))  # type: ignore[arg-type]
    if footer is None:
        raise InternalError(f"the sealed recording {prefix}/{RECORDING} has no readable footer: seal the run again")
    return footer


def _read_hot(run_id: str, hot: HotRecording) -> RunChunks:
    """A hot run's chunks from the chunk index ingest keeps beside its file (no chunk decoded)."""
    rows: list[IndexRow] = []
    uncompressed: dict[bytes, int] = {}
    metas = []
    for entry in hot.chunk_index().entries:
        meta = entry.meta
        if meta is None or entry.kind != CHUNK or entry.store_kind != RECORDING_STORE:
            continue
        if meta.chunk_id in uncompressed:
            continue  # a chunk sent twice is kept once, as sealing keeps it
        metas.append(meta)
        uncompressed[meta.chunk_id] = meta.uncompressed_size
        rows.append(entry.row)
    return RunChunks(run_id, tuple(rows), uncompressed, rerun_order(sorbet_schema(metas)))
