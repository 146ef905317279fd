"""A dataset's segment table: one row per run (a snapshot version's: per episode), with Rerun's
columns and the fleet's.

Columns, named and typed as Rerun's own server does (the golden tests compare):
- `rerun_segment_id`, `rerun_layer_names`, `rerun_storage_urls`, `rerun_last_updated_at`,
  `rerun_num_chunks`, `rerun_size_bytes`;
- the runs' recording properties, `property:NAME:COMPONENT` for `rr.send_property(NAME, ...)` and
  `property:COMPONENT` for the recording's own (`property:RecordingInfo:start_time`), each a list
  column with the `rerun:*` metadata of the property entity it comes from;
- what the depot knows of each run, as the properties of a `depot` property entity:
  `property:depot:robot_id`, `:tier`, `:status`, `:started_at`, `:ended_at`, `:pinned`;
- what the corpus knows: `property:depot:metric:NAME` per metric some run of the dataset has
  (list<float64>, or list<utf8> for a metric some run holds as text) and `property:depot:tags`
  (list<utf8>, sorted), so a client filters segments on them as on any property column
  (`array_has(col("property:depot:tags"), lit("night-shift"))`, `col("property:depot:metric:distance_m")[0] > 100`);
- per timeline, `TIMELINE:start` and `TIMELINE:end` with their `rerun:index*` metadata;
- of a snapshot version (`snapshots.py`), a row per episode, with its run's columns as above and the
  episode's facts: `property:depot:episode` (its number), `:run_id`, `:split`, `:timeline`,
  `:window_start`, `:window_end` (null for a whole run), `:event_id`, `:missing` and `:missing_why`
  (its run deleted since); its `rerun_num_chunks` and `rerun_size_bytes` are the episode's, its
  timeline's columns its window (within the run's range), `rerun_storage_urls` the download of
  exactly its chunks.

Everything comes from catalog rows (runs, run_timelines, run_entities, run_metrics, run_tags, the
snapshot's episodes): no run file is opened.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pyarrow as pa
from sqlalchemy.orm import Session

from catalog.dataset_columns import property_values
from catalog.db import session_scope
from catalog.models import Dataset
from core.errors import InvalidArgumentError
from services.auth.scopes import Principal
from services.redap import datasets, snapshots
from services.redap.dataframe import dataframe_part, schema_proto
from services.redap.datasets import EpisodeFacts, Runs, SegmentRow
from services.redap.depot import Depot
from services.redap.entries import depot_url
from services.redap.pb import cloud_pb2
from services.redap.snapshots import SnapshotVersion
from services.redap.tuid import Tuid, epoch_ns
from services.rrd.manifest import PROPERTIES_ENTITY

LAYER = "base"  # Rerun's name for a segment's first layer; a run is one recording, one layer
PAGE_ROWS = 1000  # runs read from the catalog at a time
FIRST_PAGE_ROWS = 100  # the first page: the table's first part goes out before a whole page is read
PART_BYTES = 4 << 20  # a response's table is cut below this many bytes
DEPOT_PROPERTY = "depot"  # the property entity the depot's own facts are shown under
METRIC_PREFIX = "metric:"  # a run metric's component under the depot's property entity
RECORDING_PROPERTY = "recording"  # how the catalog keys the `/__properties` entity's own components

Cell = Any  # one value of a column, as pyarrow takes it


@dataclass(frozen=True)
class Column:
    field: pa.Field
    value: Callable[[SegmentRow], Cell]

    @property
    def name(self) -> str:
        return str(self.field.name)


def _strings() -> pa.DataType:
    return pa.list_(pa.field("item", pa.utf8(), nullable=False))


def _fixed_columns(depot: Depot) -> list[Column]:
    def storage_url(row: SegmentRow) -> list[str]:
        path = row.episode.download if row.episode is not None else f"/v1/runs/{row.run_id}/recording.rrd"
        return [depot_url(depot, path)]

    return [
        Column(pa.field("rerun_segment_id", pa.utf8(), nullable=False), lambda row: row.segment_id),
        Column(pa.field("rerun_layer_names", _strings(), nullable=False), lambda row: [LAYER]),
        Column(pa.field("rerun_storage_urls", _strings(), nullable=False), storage_url),
        Column(
            pa.field("rerun_last_updated_at", pa.timestamp("ns"), nullable=False),
            lambda row: epoch_ns(row.updated_at),
        ),
        Column(pa.field("rerun_num_chunks", pa.uint64(), nullable=False), lambda row: max(row.chunks, 0)),
        Column(pa.field("rerun_size_bytes", pa.uint64(), nullable=False), lambda row: max(row.bytes, 0)),
    ]


# --- property columns ------------------------------------------------------------------------


def property_column_name(prop: str, component: str) -> str:
    return f"property:{component}" if prop == RECORDING_PROPERTY else f"property:{prop}:{component}"


def property_entity(prop: str) -> str:
    return PROPERTIES_ENTITY if prop == RECORDING_PROPERTY else f"{PROPERTIES_ENTITY}/{prop}"


# Component types of the recording's own properties (the catalog keeps values, not types).
KNOWN_COMPONENT_TYPES = {
    "RecordingInfo:start_time": "rerun.components.Timestamp",
    "RecordingInfo:name": "rerun.components.Name",
}


def _property_field(prop: str, component: str, item: pa.DataType, archetypes: set[str]) -> pa.Field:
    metadata = {
        "rerun:component": component,
        "rerun:entity_path": property_entity(prop),
        "rerun:kind": "data",
    }
    prefix, colon, _ = component.partition(":")
    if colon:  # `Archetype:field`: the archetype logged on that entity with that short name
        archetype = next((a for a in sorted(archetypes) if a.rpartition(".")[2] == prefix), None)
        if archetype is None and prefix == "RecordingInfo":
            archetype = "rerun.archetypes.RecordingInfo"
        if archetype is not None:
            metadata["rerun:archetype"] = archetype
    if component in KNOWN_COMPONENT_TYPES and prop == RECORDING_PROPERTY:
        metadata["rerun:component_type"] = KNOWN_COMPONENT_TYPES[component]
    return pa.field(property_column_name(prop, component), pa.list_(item), nullable=True, metadata=metadata)


NONFINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}  # how the catalog writes them


def item_type(kinds: set[str]) -> pa.DataType:
    """The Arrow type of a property's values from the kinds of values the runs hold."""
    if kinds == {"bool"}:
        return pa.bool_()
    if kinds == {"int"}:
        return pa.int64()
    if kinds and kinds <= {"int", "float", "nonfinite"} and kinds & {"float", "nonfinite"} and kinds != {"nonfinite"}:
        return pa.float64()
    return pa.utf8()


def _convert(item: Any, kind: pa.DataType) -> Any:
    if item is None:
        return None
    if pa.types.is_string(kind):
        return item if isinstance(item, str) else json.dumps(item, sort_keys=True)
    if pa.types.is_floating(kind):
        return NONFINITE[item] if isinstance(item, str) else float(item)
    return item


def _property_column(prop: str, component: str, kinds: set[str], archetypes: set[str]) -> Column:
    item = item_type(kinds)

    def value(row: SegmentRow) -> Cell:
        values = row.properties.get(prop)
        found = property_values(values.get(component)) if isinstance(values, dict) else None
        return None if found is None else [_convert(v, item) for v in found]

    return Column(_property_field(prop, component, item, archetypes), value)


def recording_property_columns(session: Session, runs: str | Runs) -> list[Column]:
    """A column per property component any of the runs holds (the depot's own column names win)."""
    kinds = datasets.property_kinds(session, runs, PAGE_ROWS)
    archetypes = datasets.property_archetypes(session, runs)
    return [
        _property_column(prop, component, found, archetypes.get(property_entity(prop), set()))
        for (prop, component), found in kinds.items()
        if prop != DEPOT_PROPERTY
    ]


def _depot_column(component: str, item: pa.DataType, value: Callable[[SegmentRow], Any]) -> Column:
    def cell(row: SegmentRow) -> Cell:
        found = value(row)
        return None if found is None else [found]

    return Column(_property_field(DEPOT_PROPERTY, component, item, set()), cell)


def depot_columns() -> list[Column]:
    """What the catalog knows of each run, beside what the run itself says."""

    def ns(moment: Any) -> int | None:
        return epoch_ns(moment) if moment is not None else None

    return [
        _depot_column("robot_id", pa.utf8(), lambda row: row.robot_id),
        _depot_column("tier", pa.utf8(), lambda row: row.tier),
        _depot_column("status", pa.utf8(), lambda row: row.status),
        _depot_column("started_at", pa.timestamp("ns"), lambda row: ns(row.started_at)),
        _depot_column("ended_at", pa.timestamp("ns"), lambda row: ns(row.ended_at)),
        _depot_column("pinned", pa.bool_(), lambda row: row.pinned),
    ]


def _metric_column(metric: str, text: bool) -> Column:
    item = pa.utf8() if text else pa.float64()

    def cell(row: SegmentRow) -> Cell:
        found = row.metrics.get(metric)
        if found is None:
            return None
        value, text_value = found
        if text:
            return [text_value if text_value is not None else _convert(value, item)]
        return None if value is None else [value]

    return Column(_property_field(DEPOT_PROPERTY, f"{METRIC_PREFIX}{metric}", item, set()), cell)


def corpus_columns(session: Session, runs: str | Runs) -> list[Column]:
    """The runs' metrics, a column each, and their tags."""
    tags = Column(_property_field(DEPOT_PROPERTY, "tags", pa.utf8(), set()), lambda row: row.tags or None)
    return [tags, *(_metric_column(metric, text) for metric, text in datasets.metric_kinds(session, runs).items())]


def _episode_column(component: str, item: pa.DataType, value: Callable[[EpisodeFacts], Any]) -> Column:
    def cell(row: SegmentRow) -> Cell:
        found = value(row.episode) if row.episode is not None else None
        return None if found is None else [found]

    return Column(_property_field(DEPOT_PROPERTY, component, item, set()), cell)


def episode_columns() -> list[Column]:
    """What a snapshot version says of each of its episodes."""
    return [
        _episode_column("episode", pa.int64(), lambda e: e.index),
        _depot_column("run_id", pa.utf8(), lambda row: row.run_id),
        _episode_column("split", pa.utf8(), lambda e: e.split),
        _episode_column("timeline", pa.utf8(), lambda e: e.timeline),
        _episode_column("window_start", pa.int64(), lambda e: e.start),
        _episode_column("window_end", pa.int64(), lambda e: e.end),
        _episode_column("event_id", pa.utf8(), lambda e: e.event_id),
        _episode_column("missing", pa.bool_(), lambda e: e.missing_why is not None),
        _episode_column("missing_why", pa.utf8(), lambda e: e.missing_why),
    ]


# --- timeline columns ------------------------------------------------------------------------

INDEX_TYPES = {"sequence": pa.int64(), "timestamp": pa.timestamp("ns"), "duration": pa.duration("ns")}


def _timeline_column(timeline: str, kind: str, marker: str) -> Column:
    metadata = {"rerun:index": timeline, "rerun:index_kind": kind, "rerun:index_marker": marker, "rerun:kind": "index"}
    at = 1 if marker == "start" else 2

    def value(row: SegmentRow) -> Cell:
        found = row.timelines.get(timeline)
        return found[at] if found is not None and found[0] == kind else None  # another type: not this column's

    return Column(pa.field(f"{timeline}:{marker}", INDEX_TYPES[kind], nullable=True, metadata=metadata), value)


def timeline_columns(session: Session, runs: str | Runs) -> list[Column]:
    return [
        _timeline_column(timeline, kind, marker)
        for timeline, kind in datasets.timeline_types(session, runs).items()
        if kind in INDEX_TYPES
        for marker in ("start", "end")
    ]


# --- the table -------------------------------------------------------------------------------


class SegmentTable:
    """The segment table's columns, in order, and how to fill them from catalog rows."""

    def __init__(self, columns: list[Column]) -> None:
        self.columns = columns
        self.schema = pa.schema([c.field for c in columns])
        self.names = {c.name for c in columns}

    def project(self, names: list[str]) -> SegmentTable:
        """Only `names`, in that order (all when empty); INVALID_ARGUMENT for a column asked twice
        or one the table does not have, as Rerun's servers answer."""
        if not names:
            return self
        by_name = {c.name: c for c in self.columns}
        seen: set[str] = set()
        for name in names:
            if name in seen:
                raise InvalidArgumentError(f"column {name!r} is asked for twice: name each column once")
            if name not in by_name:
                raise InvalidArgumentError(
                    f"the segment table has no column {name!r}: GetSegmentTableSchema lists its columns"
                )
            seen.add(name)
        return SegmentTable([by_name[name] for name in names])

    def batch(self, rows: list[SegmentRow]) -> pa.RecordBatch:
        arrays = [pa.array([c.value(row) for row in rows], type=c.field.type) for c in self.columns]
        return pa.RecordBatch.from_arrays(arrays, schema=self.schema)


def segment_table(
    session: Session, runs: str | Runs, depot: Depot, *, properties: bool = True, episodes: bool = False
) -> SegmentTable:
    """The segment table of a dataset whose segments are of these runs: Rerun's columns, the
    property columns (the recording's, the depot's, with `episodes` a snapshot's) sorted by name,
    then the timelines' sorted by name. `properties=False` leaves the recording's properties out
    (reading them means reading every run's row)."""
    found = recording_property_columns(session, runs) if properties else []
    ours = [*depot_columns(), *corpus_columns(session, runs), *(episode_columns() if episodes else [])]
    props = sorted([*found, *ours], key=lambda c: c.name)
    timelines = sorted(timeline_columns(session, runs), key=lambda c: c.name)
    return SegmentTable([*_fixed_columns(depot), *props, *timelines])


def _table(
    session: Session, dataset: Dataset | SnapshotVersion, depot: Depot, *, properties: bool = True
) -> SegmentTable:
    if isinstance(dataset, SnapshotVersion):
        return segment_table(session, dataset.runs, depot, properties=properties, episodes=True)
    return segment_table(session, dataset.name, depot, properties=properties)


def table_schema(depot: Depot, principal: Principal, entry: Tuid) -> cloud_pb2.GetSegmentTableSchemaResponse:
    with session_scope(depot.catalog) as session:
        table = _table(session, snapshots.find_dataset(session, entry), depot)
    return cloud_pb2.GetSegmentTableSchemaResponse(schema=schema_proto(table.schema))


# --- scanning --------------------------------------------------------------------------------


def _wanted(request: cloud_pb2.ScanSegmentTableRequest) -> tuple[list[str] | None, frozenset[str]]:
    """(the only segments to scan, or None for all; the segments to skip)."""
    if not request.HasField("segment_id_filter"):
        return None, frozenset()
    strategy = request.segment_id_filter.WhichOneof("strategy")
    if strategy == "scan_only":
        return sorted(set(request.segment_id_filter.scan_only.segment_ids)), frozenset()
    if strategy == "skip":
        return None, frozenset(request.segment_id_filter.skip.segment_ids)
    return None, frozenset()


def _row_pages(depot: Depot, name: str, only: list[str] | None, skip: frozenset[str]) -> Iterator[list[SegmentRow]]:
    """An application's rows to scan, a page at a time, each page read in a short transaction of its own."""
    if only is not None:
        for start in range(0, len(only), PAGE_ROWS):
            with session_scope(depot.catalog) as session:
                yield datasets.segment_rows_named(session, name, only[start : start + PAGE_ROWS])
        return
    after: str | None = None
    page = FIRST_PAGE_ROWS
    while True:
        with session_scope(depot.catalog) as session:
            rows = datasets.segment_rows(session, name, after, page)
        if not rows:
            return
        yield [row for row in rows if row.run_id not in skip]
        after, page = rows[-1].run_id, PAGE_ROWS


def _episode_pages(
    depot: Depot, version: SnapshotVersion, only: list[str] | None, skip: frozenset[str]
) -> Iterator[list[SegmentRow]]:
    """A snapshot version's rows to scan (its episodes, in order), a page at a time."""
    if only is not None:
        for start in range(0, len(only), PAGE_ROWS):
            with session_scope(depot.catalog) as session:
                named = snapshots.episodes_named(session, version, only[start : start + PAGE_ROWS])
                yield snapshots.episode_rows(session, version, named)
        return
    after, size = -1, FIRST_PAGE_ROWS
    while True:
        with session_scope(depot.catalog) as session:
            page = snapshots.episode_page(session, version, after, size)
            rows = snapshots.episode_rows(session, version, page)
        if not rows:
            return
        yield [row for row in rows if row.segment_id not in skip]
        after, size = max(row.episode.index for row in rows if row.episode is not None), PAGE_ROWS


def _parts(batch: pa.RecordBatch) -> Iterator[pa.RecordBatch]:
    """`batch` cut into parts of at most about PART_BYTES each."""
    count = max(1, math.ceil(batch.nbytes / PART_BYTES))
    rows = max(1, math.ceil(batch.num_rows / count))
    for start in range(0, batch.num_rows, rows):
        yield batch.slice(start, rows)


def scan(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.ScanSegmentTableRequest
) -> Iterator[cloud_pb2.ScanSegmentTableResponse]:
    """The segment table, projected and filtered by segment id, in parts of bounded size; a table
    with no rows is one empty part (its columns still say what it holds)."""
    asked = list(request.columns)
    with session_scope(depot.catalog) as session:
        dataset = snapshots.find_dataset(session, entry)
        table = _table(session, dataset, depot, properties=False)
        if not asked or not set(asked) <= table.names:  # the recording's properties are asked for (or unknown)
            table = _table(session, dataset, depot)
        version = dataset if isinstance(dataset, SnapshotVersion) else None
        name = dataset.name
    table = table.project(asked)
    only, skip = _wanted(request)
    pages = _episode_pages(depot, version, only, skip) if version is not None else _row_pages(depot, name, only, skip)
    sent = False
    for rows in pages:
        if rows:
            for part in _parts(table.batch(rows)):
                sent = True
                yield cloud_pb2.ScanSegmentTableResponse(data=dataframe_part(part))
    if not sent:
        yield cloud_pb2.ScanSegmentTableResponse(data=dataframe_part(table.batch([])))
