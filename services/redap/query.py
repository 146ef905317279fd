"""Querying from the SDK: a dataset's schema (GetDatasetSchema) and the chunks a query may need
(FindChunks, and QueryDataset for clients that do not know FindChunks), from the runs' chunk
indexes; the client fetches the chunks and resolves the rows itself.

Both candidate calls become one `Plan` (contents, segments, and what in time), checked as Rerun's
own server checks it (the same calls are refused, with messages naming the field), then answered a
segment at a time, in parts of bounded size. Segments are runs, or a snapshot version's episodes
(`snapshots.py`: each the chunks of its run it reads, and nothing else: the plan selects among
them as among a run's): an explicit list selects the segments named (an unknown id selects nothing,
as the protocol says, so a filter on segment ids never fails); a segment that cannot be read now
(its run cold and not restored, or deleted since a snapshot listed it) fails a query naming it, and
is left out of one over every segment. Requests name entities as `/world/points` or
`world/points`, alike."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.db import session_scope
from catalog.models import Run, RunTimeline
from core.errors import InvalidArgumentError, UnimplementedError
from services.auth.scopes import Principal
from services.redap import direct as direct_reads
from services.redap.candidate_table import candidate_batches, find_chunks_schema, query_dataset_schema
from services.redap.candidates import (
    Contents,
    Everything,
    Mode,
    Samples,
    StaticOnly,
    TimeRange,
    normal_entity_path,
    select,
)
from services.redap.dataframe import dataframe_part, schema_proto
from services.redap.datasets import Runs, application_runs
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.schema import merge_schemas
from services.redap.snapshots import SnapshotVersion, episode_page, episode_sources, find_dataset
from services.redap.sources import DatasetView, SegmentSource, dataset_sources, run_chunks, segment_schema
from services.redap.tuid import Tuid
from services.runs.served import count_served

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Plan:
    """What a candidate query selects: `segments` None is every segment; `per_segment` (a
    resampling) gives each listed segment its own sample times."""

    contents: Contents
    segments: frozenset[str] | None
    mode: Mode
    per_segment: Mapping[str, Samples] | None = None

    @property
    def timeline(self) -> str | None:
        """The timeline the query names (checked against the dataset's), if any."""
        return self.mode.timeline if isinstance(self.mode, TimeRange | Samples) else None

    def mode_for(self, segment: str) -> Mode | None:
        """What is selected of `segment`; None: nothing."""
        if self.per_segment is not None:
            return self.per_segment.get(segment)
        return self.mode if self.segments is None or segment in self.segments else None


# --- the three calls ---------------------------------------------------------------------------


def dataset_schema(depot: Depot, principal: Principal, entry: Tuid) -> cloud_pb2.GetDatasetSchemaResponse:
    """The merge of the dataset's runs' schemas (runs that cannot be read now left out)."""
    view = _dataset(depot, entry)
    schemas = []
    for segment in view.segments:
        if segment.source.unreadable is not None:
            log.info("dataset %s: schema without %s (%s)", view.name, segment.segment_id, segment.source.unreadable)
            continue
        schemas.append(segment_schema(depot, segment))
    return cloud_pb2.GetDatasetSchemaResponse(schema=schema_proto(merge_schemas(schemas)))


def find_chunks(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.FindChunksRequest
) -> Iterator[cloud_pb2.FindChunksResponse]:
    plan = find_chunks_plan(request)
    view = _dataset(depot, entry, plan.segments)
    _check_timeline(view, plan.timeline)
    direct = direct_reads.wanted_by_find_chunks(request)
    for batch in _candidates(depot, view, plan, find_chunks_schema(), plan.timeline, direct):
        yield cloud_pb2.FindChunksResponse(data=dataframe_part(batch))


def query_dataset(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.QueryDatasetRequest
) -> Iterator[cloud_pb2.QueryDatasetResponse]:
    plan = query_dataset_plan(request)
    view = _dataset(depot, entry, plan.segments)
    _check_timeline(view, plan.timeline)
    timeline = plan.timeline or _start_column_timeline(request.scan_parameters.columns, view.timelines)
    direct = direct_reads.wanted_by_query_dataset(request)
    for batch in _candidates(depot, view, plan, query_dataset_schema(timeline), timeline, direct):
        yield cloud_pb2.QueryDatasetResponse(data=dataframe_part(batch))


# --- answering a plan --------------------------------------------------------------------------


def _dataset(depot: Depot, entry: Tuid, only: frozenset[str] | None = None) -> DatasetView:
    """The dataset and its segments (`only` those named, when a query names its segments)."""
    with session_scope(depot.catalog) as session:
        dataset = find_dataset(session, entry)
        if isinstance(dataset, SnapshotVersion):
            segments = episode_sources(depot, session, dataset, only)
            empty = not episode_page(session, dataset, -1, 1)
            return DatasetView(dataset.entry_name, _timelines(session, dataset.runs), segments, empty)
        sources = dataset_sources(depot, session, dataset, depot.clock(), only)
        held = sa.select(Run.id).where(application_runs(dataset.name)).limit(1)
        empty = session.scalar(held) is None
        segments = [SegmentSource(source.run_id, source) for source in sources]
        return DatasetView(dataset.name, _timelines(session, application_runs(dataset.name)), segments, empty)


def _timelines(session: Session, runs: Runs) -> frozenset[str]:
    query = sa.select(RunTimeline.name).join(Run, Run.id == RunTimeline.run_id).where(runs).distinct()
    return frozenset(session.scalars(query))


def _check_timeline(view: DatasetView, timeline: str | None) -> None:
    if timeline is not None and not view.empty and timeline not in view.timelines:
        known = ", ".join(sorted(view.timelines)) or "none (its runs hold static data only)"
        raise InvalidArgumentError(f"unknown timeline {timeline!r}: dataset {view.name!r} has {known}")


def _candidates(
    depot: Depot, view: DatasetView, plan: Plan, schema: pa.Schema, timeline: str | None, direct: bool
) -> Iterator[pa.RecordBatch]:
    """Each selected segment's candidate rows, a segment at a time; one empty part when none is
    found (as Rerun's server answers: the client learns the columns either way). `direct`: the
    client takes URLs to read a whole sealed run's chunks from the bucket (`direct.py`)."""
    sent = False
    for segment in view.segments:
        mode = plan.mode_for(segment.segment_id)
        if mode is None:
            continue
        source = segment.source
        if source.unreadable is not None and plan.segments is None:
            log.info("dataset %s: query without %s (%s)", view.name, segment.segment_id, source.unreadable)
            continue
        found = run_chunks(depot, source)  # an explicitly named segment that cannot be read fails the query
        rows = select(segment.rows(found), plan.contents, mode)
        url = direct_reads.direct_url(depot, source) if direct and segment.chunk_ids is None and rows else None
        if url is not None:
            count_served("direct", len(rows), sum(r.length for r in rows))
        for batch in candidate_batches(schema, segment.segment_id, rows, found.uncompressed, timeline, url):
            sent = True
            yield batch
    if not sent:
        yield pa.RecordBatch.from_pylist([], schema=schema)


# --- FindChunks' request -----------------------------------------------------------------------


def find_chunks_plan(request: cloud_pb2.FindChunksRequest) -> Plan:
    """The plan of a FindChunks request; INVALID_ARGUMENT naming the field a request gets wrong."""
    if not request.HasField("contents"):
        raise InvalidArgumentError("`contents` is required: `all`, or `explicit` entities")
    contents = _contents(request.contents)
    which = request.WhichOneof("mode")
    if which == "static":
        return Plan(contents, _segments(request.static, "static"), StaticOnly())
    if which == "range":
        found = request.range
        start = found.start_inclusive if found.HasField("start_inclusive") else None
        end = found.end_inclusive if found.HasField("end_inclusive") else None
        fill = _fill(found.fill_mode, "range.fill_mode")
        if start is not None and end is not None and end < start:
            raise InvalidArgumentError(
                f"`range.end_inclusive` ({end}) must not be before `range.start_inclusive` ({start})"
            )
        if fill and start is None:
            raise InvalidArgumentError("`range.fill_mode` FILL_MODE_LATEST_AT needs `range.start_inclusive`")
        mode = TimeRange(_timeline(found.timeline, "range.timeline"), start, end, fill)
        return Plan(contents, _segments(found, "range"), mode)
    if which == "samples":
        return _samples_plan(contents, request.samples)
    raise InvalidArgumentError("`mode` is required: `static`, `range` or `samples`")


def _samples_plan(contents: Contents, samples: cloud_pb2.SegmentSamplesSelection) -> Plan:
    timeline = _timeline(samples.timeline, "samples.timeline")
    fill = _fill(samples.fill_mode, "samples.fill_mode")
    times: dict[str, list[int]] = {}
    for entry in samples.segments:
        if not entry.segment_id.id:
            raise InvalidArgumentError("`samples.segments[].segment_id` is required")
        times.setdefault(entry.segment_id.id, []).extend(entry.values)
    per_segment = {segment: Samples(timeline, tuple(values), fill) for segment, values in times.items()}
    return Plan(contents, frozenset(per_segment), Samples(timeline, (), fill), per_segment)


def _contents(selection: cloud_pb2.ContentSelection) -> Contents:
    which = selection.WhichOneof("selection")
    if which == "all":
        return Contents()
    if which != "explicit":
        raise InvalidArgumentError("`contents` is required: `all`, or `explicit` entities")
    entities: dict[str, frozenset[str] | None] = {}
    for entity in selection.explicit.entities:
        path = normal_entity_path(entity.entity_path.path)
        if path in entities:
            raise InvalidArgumentError(f"entity path {path} is named twice in `contents`")
        components = entity.WhichOneof("components")
        if components is None:
            raise InvalidArgumentError(f"`contents` entity {path} needs its components: `all` or `explicit`")
        ids = frozenset(entity.explicit.ids) if components == "explicit" else None
        if ids is not None and "" in ids:
            raise InvalidArgumentError(f"`contents` entity {path}: component ids must not be empty")
        entities[path] = ids
    return Contents(entities)


def _segments(parent: cloud_pb2.StaticSelection | cloud_pb2.RangeSelection, name: str) -> frozenset[str] | None:
    which = parent.segments.WhichOneof("selection") if parent.HasField("segments") else None
    if which is None:
        raise InvalidArgumentError(f"`{name}.segments` is required: `all`, or `explicit` segment ids")
    return None if which == "all" else frozenset(s.id for s in parent.segments.explicit.ids)


def _fill(fill_mode: int, name: str) -> bool:
    if fill_mode in (cloud_pb2.FILL_MODE_UNSPECIFIED, cloud_pb2.FILL_MODE_NONE):
        return False
    if fill_mode == cloud_pb2.FILL_MODE_LATEST_AT:
        return True
    if fill_mode == cloud_pb2.FILL_MODE_EARLIEST_AT:
        raise UnimplementedError(f"`{name}` FILL_MODE_EARLIEST_AT is not served: use FILL_MODE_LATEST_AT or none")
    raise InvalidArgumentError(f"`{name}` {fill_mode} is not a fill mode")


def _timeline(name: str, field: str) -> str:
    if not name:
        raise InvalidArgumentError(f"`{field}` is required: the name of a timeline of the dataset")
    return name


# --- QueryDataset's request --------------------------------------------------------------------


def query_dataset_plan(request: cloud_pb2.QueryDatasetRequest) -> Plan:
    """The plan of a (deprecated) QueryDataset request: the FindChunks selection it stands for."""
    _refuse_unmapped(request)
    if request.select_all_entity_paths and request.entity_paths:
        raise InvalidArgumentError("`select_all_entity_paths` is true, but `entity_paths` is not empty: set one")
    # fuzzy_descriptors narrow components; left out, the answer is a superset, as the protocol allows
    contents = (
        Contents()
        if request.select_all_entity_paths
        else Contents({normal_entity_path(p.path): None for p in request.entity_paths})
    )
    segment_ids = [s.id for s in request.segment_ids]
    segments = frozenset(segment_ids) or None
    query = request.query if request.HasField("query") else None
    latest = query.latest_at if query is not None and query.HasField("latest_at") else None
    ranged = query.range if query is not None and query.HasField("range") else None
    if latest is not None and latest.per_segment_values:
        return _per_segment_plan(contents, segment_ids, latest, ranged)
    latest_timeline = latest.index.timeline.name if latest is not None else ""
    if latest is not None and latest_timeline and not latest.HasField("at"):
        raise InvalidArgumentError("`latest_at.at` must be set when `latest_at.index` names a timeline")
    if ranged is not None:
        return Plan(contents, segments, _range_mode(ranged, latest if latest_timeline else None))
    if latest is not None and latest_timeline:
        return Plan(contents, segments, TimeRange(latest_timeline, latest.at, latest.at, True))
    return Plan(contents, segments, StaticOnly() if latest is not None else Everything())


def _refuse_unmapped(request: cloud_pb2.QueryDatasetRequest) -> None:
    """What QueryDataset asks that has no equivalent in a chunk selection: refused, as by Rerun."""
    if request.chunk_ids:
        raise InvalidArgumentError("`chunk_ids` must be empty: select chunks by segment, entity and time")
    for flag in ("exclude_static_data", "exclude_temporal_data"):
        if getattr(request, flag):
            raise InvalidArgumentError(f"`{flag}` must be false: it has no equivalent in a chunk selection")
    scan = request.scan_parameters
    for name in ("filter", "limit_offset", "limit_len"):
        if scan.HasField(name):
            raise InvalidArgumentError(f"`scan_parameters.{name}` must be unset: filter the rows in the client")
    if scan.order_by:
        raise InvalidArgumentError("`scan_parameters.order_by` must be empty: order the rows in the client")


def _range_mode(ranged: cloud_pb2.QueryRange, latest: cloud_pb2.QueryLatestAt | None) -> TimeRange:
    timeline = _timeline(ranged.index.timeline.name, "range.index")
    if not ranged.HasField("index_range"):
        raise InvalidArgumentError("`range.index_range` is required for a range query")
    start, end = ranged.index_range.start, ranged.index_range.end
    if end < start:
        raise InvalidArgumentError(f"`range.index_range` ends ({end}) before it starts ({start})")
    if latest is None:
        return TimeRange(timeline, start, end)
    if latest.index.timeline.name != timeline or latest.at != start:
        raise InvalidArgumentError(
            "`latest_at` with a `range` must be at the range's start on the same timeline (a latest-at fill)"
        )
    return TimeRange(timeline, start, end, True)


def _per_segment_plan(
    contents: Contents, segment_ids: list[str], latest: cloud_pb2.QueryLatestAt, ranged: cloud_pb2.QueryRange | None
) -> Plan:
    timeline = _timeline(latest.index.timeline.name, "latest_at.index")
    values = latest.per_segment_values
    if latest.HasField("at") or ranged is not None:
        raise InvalidArgumentError("`latest_at.per_segment_values` excludes `latest_at.at` and `range`")
    if len(values) != len(segment_ids):
        raise InvalidArgumentError(
            f"`latest_at.per_segment_values` has {len(values)} lists for {len(segment_ids)} `segment_ids`"
        )
    if len(set(segment_ids)) != len(segment_ids):
        raise InvalidArgumentError("`segment_ids` must not repeat a segment with `latest_at.per_segment_values`")
    # a segment with no values selects nothing of it (`select` answers no rows for no sample times)
    per_segment = {s: Samples(timeline, tuple(v.values), True) for s, v in zip(segment_ids, values, strict=True)}
    return Plan(contents, frozenset(segment_ids), Samples(timeline, (), True), per_segment)


def _start_column_timeline(columns: Iterable[str], timelines: frozenset[str]) -> str | None:
    """The timeline of a `{timeline}:start` column asked for by name, when exactly one is."""
    named = {c[: -len(":start")] for c in columns if c.endswith(":start")}
    known = named & timelines
    return next(iter(known)) if len(known) == 1 else None
