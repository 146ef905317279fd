"""One run's scalars and text logs, as its page plots and lists them: a sealed run's from its
analytics tables (the `scalars` and `text_logs` Parquet written at promotion), a hot run's read
from its file now with the same extraction (`Extractor`), so both look alike."""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from services.analytics.extract import LOG_TIME, extract_file
from services.hot.read import HotRuns
from services.storage.objectstore import ObjectStore

MAX_POINTS = 2000  # per line: more are thinned evenly (the first and last kept)
MAX_ENTITIES = 24  # plots on one page
MAX_LOGS = 200  # the newest text logs shown
MAX_TABLE_BYTES = 256 << 20  # a run's analytics file, or hot file, read for its page at most


@dataclass(frozen=True)
class Line:
    """One scalar line of an entity (its instance, when an entity logs several)."""

    name: str
    points: list[tuple[float, float]]
    logged: int  # points in the run (more than `points` when thinned)


@dataclass(frozen=True)
class Plot:
    entity: str
    x: str  # the timeline on the x axis
    lines: list[Line]


@dataclass(frozen=True)
class LogLine:
    entity: str
    level: str | None
    text: str
    at: int | None  # on `RunViews.log_timeline`


@dataclass
class RunViews:
    source: str  # "analytics tables" | "hot run"
    plots: list[Plot] = field(default_factory=list)
    x: str | None = None  # the plots' timeline
    x_type: str = "sequence"
    timelines: list[str] = field(default_factory=list)  # those the plots could use
    logs: list[LogLine] = field(default_factory=list)  # oldest first, the newest last
    log_timeline: str | None = None
    log_type: str = "sequence"  # of log_timeline: how its values are written
    logs_total: int = 0
    note: str | None = None  # why something is missing


def sealed_views(
    catalog: sessionmaker[Session], warm: ObjectStore, run_id: str, timelines: dict[str, str], x: str | None = None
) -> RunViews:
    """A sealed run's plots and logs from its analytics files (`timelines`: the run's, name -> type)."""
    with session_scope(catalog) as session:
        objects = {name: (o.key, o.size) for name, o in queries.run_objects(session, run_id).items()}
    tables: dict[str, pa.Table] = {}
    views = RunViews("analytics tables")
    for name in ("scalars", "text_logs"):
        found = objects.get(f"analytics/{name}")
        if found is None:
            continue
        key, size = found
        if size > MAX_TABLE_BYTES:
            views.note = f"the run's {name} table is {size} bytes: query it on the SQL page instead"
            continue
        tables[name] = pq.read_table(io.BytesIO(warm.get_range(key)))
    return _views(views, tables.get("scalars"), tables.get("text_logs"), timelines, x)


def hot_views(hot_runs: HotRuns, run_id: str, timelines: dict[str, str], x: str | None = None) -> RunViews:
    """A hot run's plots and logs, read from its file as it stands now."""
    hot = hot_runs.hot_recording(run_id)
    views = RunViews("hot run")
    if hot is None:
        views.note = "the run is not hot on this node (another node of the depot files it)"
        return views
    if hot.size > MAX_TABLE_BYTES:
        views.note = f"the hot run is {hot.size} bytes: promote it, then its page plots from its analytics tables"
        return views
    tables = extract_file(run_id, hot.path, hot.size).tables()
    return _views(views, tables.get("scalars"), tables.get("text_logs"), {**hot.timeline_types, **timelines}, x)


def _views(
    views: RunViews, scalars: pa.Table | None, logs: pa.Table | None, timelines: dict[str, str], x: str | None
) -> RunViews:
    if scalars is not None and scalars.num_rows:
        usable = [t for t in _timeline_columns(scalars, timelines) if t in scalars.column_names]
        views.timelines = usable
        if usable:
            views.x = x if x in usable else _default_x(usable, timelines)
            views.x_type = "timestamp" if views.x == LOG_TIME else timelines.get(_timeline_of(views.x), "sequence")
            views.plots = _plots(scalars, views.x)
    if logs is not None and logs.num_rows:
        views.logs_total = logs.num_rows
        order = LOG_TIME if LOG_TIME in logs.column_names else None
        if order is None:
            order = next(iter(_timeline_columns(logs, timelines)), None)
        views.log_timeline = order
        if order is not None:
            views.log_type = "timestamp" if order == LOG_TIME else timelines.get(_timeline_of(order), "sequence")
        views.logs = _logs(logs, order)
    return views


def _timeline_of(column: str) -> str:
    return column.removeprefix("timeline_")


def _timeline_columns(table: pa.Table, timelines: dict[str, str]) -> list[str]:
    """Columns of `table` that are timelines (named after them, or `timeline_NAME` on a clash)."""
    names = set(table.column_names)
    out = []
    for name in sorted(timelines):
        if name in names and name not in ("run_id", "entity", "component", "instance", "value", "level", "text"):
            out.append(name)
        elif f"timeline_{name}" in names:
            out.append(f"timeline_{name}")
    if LOG_TIME in names and LOG_TIME not in out:
        out.append(LOG_TIME)
    return out


def _default_x(usable: list[str], timelines: dict[str, str]) -> str:
    """A sequence timeline (frames count as people read plots), else the log time, else any."""
    sequences = [t for t in usable if timelines.get(_timeline_of(t)) == "sequence"]
    if sequences:
        return sequences[0]
    return LOG_TIME if LOG_TIME in usable else usable[0]


def _numbers(column: pa.ChunkedArray) -> list[float | None]:
    if pa.types.is_timestamp(column.type) or pa.types.is_duration(column.type):
        column = pc.cast(column, pa.int64())
    return [None if v is None else float(v) for v in column.to_pylist()]


def _plots(scalars: pa.Table, x: str) -> list[Plot]:
    entities = sorted(set(scalars.column("entity").to_pylist()))[:MAX_ENTITIES]
    plots = []
    for entity in entities:
        rows = scalars.filter(pc.equal(scalars.column("entity"), entity))
        xs, ys = _numbers(rows.column(x)), _numbers(rows.column("value"))
        instances = rows.column("instance").to_pylist()
        per: dict[int, list[tuple[float, float]]] = {}
        for xv, yv, inst in zip(xs, ys, instances, strict=True):
            if xv is not None and yv is not None:
                per.setdefault(int(inst or 0), []).append((xv, yv))
        lines = [
            Line(entity if len(per) == 1 else f"{entity}[{inst}]", _thin(sorted(points)), len(points))
            for inst, points in sorted(per.items())
        ]
        if lines:
            plots.append(Plot(entity, x, lines))
    return plots


def _thin(points: list[tuple[float, float]], most: int = MAX_POINTS) -> list[tuple[float, float]]:
    if len(points) <= most:
        return points
    step = (len(points) - 1) / (most - 1)
    return [points[round(i * step)] for i in range(most)]


def _logs(logs: pa.Table, order: str | None) -> list[LogLine]:
    at = _numbers(logs.column(order)) if order else [None] * logs.num_rows
    rows = list(
        zip(
            at,
            logs.column("entity").to_pylist(),
            logs.column("level").to_pylist(),
            logs.column("text").to_pylist(),
            strict=True,
        )
    )
    rows.sort(key=lambda r: (r[0] is None, r[0] or 0.0))
    return [
        LogLine(entity, level, text or "", None if when is None else int(when))
        for when, entity, level, text in rows[-MAX_LOGS:]
    ]
