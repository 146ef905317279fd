"""Datasets and segments as the catalog holds them: a dataset is an application id (its entry id a
TUID in the `datasets` table), a segment one of its runs; or a snapshot version (`snapshots.py`),
a segment one of its episodes. The segment table's facts are read for a set of runs given as a
condition on `Run` (`Runs`): an application's runs that hold data, or the runs a version reads."""

from __future__ import annotations

import datetime as dt
import itertools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy import select
from sqlalchemy.orm import Session

from catalog import queries
from catalog.dataset_columns import dataset_columns, json_names, json_object, property_items, property_key
from catalog.models import Dataset, DatasetEpisode, Run, RunEntity, RunMetric, RunTag, RunTimeline
from core.clock import aware
from core.errors import NotFoundError
from core.ids import possible_ids
from core.states import Tier
from services.redap.tuid import Tuid
from services.rrd.manifest import PROPERTIES_ENTITY

Runs = sa.ColumnElement[bool]  # which runs a dataset's segments are read from, as a condition on Run


def application_runs(name: str) -> Runs:
    """The runs of application `name` that hold data (deleted runs keep a tombstone row, not a segment)."""
    return sa.and_(Run.application_id == name, Run.tier != Tier.DELETED)


def version_runs(name: str, version: int) -> Runs:
    """The runs snapshot version `name@version` reads, deleted since or not."""
    listed = select(DatasetEpisode.run_id).where(DatasetEpisode.name == name, DatasetEpisode.version == version)
    return Run.id.in_(listed)


def _runs(runs: str | Runs) -> Runs:
    return application_runs(runs) if isinstance(runs, str) else runs


def dataset_by_entry(session: Session, entry: Tuid) -> Dataset:
    """The dataset an `x-rerun-entry-id` names; NOT_FOUND naming how to list them."""
    found = session.scalars(select(Dataset).where(Dataset.entry_id == str(entry))).first()
    if found is None:
        raise NotFoundError(f"no dataset has entry id {entry}: list the catalog's entries (FindEntries) for their ids")
    return found


def segment_run(session: Session, dataset: Dataset, segment_id: str) -> Run:
    """The run a segment id names, if it is one of the dataset's; NOT_FOUND otherwise."""
    run = queries.get_run(session, segment_id)
    if run is None or run.application_id != dataset.name:
        raise NotFoundError(f"dataset {dataset.name!r} has no segment {segment_id!r}")
    return run


def dataset_runs(session: Session, dataset: Dataset) -> list[Run]:
    """The dataset's runs that still hold data (deleted runs keep a tombstone row, not a segment)."""
    return list(session.scalars(select(Run).where(application_runs(dataset.name)).order_by(Run.id)))


# --- the segment table's rows, read in pages so a fleet's whole history is never in memory -----


@dataclass(frozen=True)
class SegmentRow:
    """What the segment table shows of one run, read from its catalog rows alone."""

    run_id: str
    robot_id: str
    status: str
    tier: str
    started_at: dt.datetime | None
    ended_at: dt.datetime | None
    pinned: bool
    chunks: int
    bytes: int
    updated_at: dt.datetime
    properties: dict[str, Any]  # property name -> component -> value ("recording": `/__properties`)
    timelines: dict[str, tuple[str, int, int]]  # name -> (type, min, max)
    metrics: dict[str, tuple[float | None, str | None]] = field(default_factory=dict)  # name -> (value, text)
    tags: list[str] = field(default_factory=list)  # sorted
    episode: EpisodeFacts | None = None  # a snapshot's segment: the episode of the run it is

    @property
    def segment_id(self) -> str:
        return self.episode.segment_id if self.episode is not None else self.run_id


@dataclass(frozen=True)
class EpisodeFacts:
    """What the segment table shows of a snapshot's episode besides its run's facts."""

    segment_id: str
    index: int
    split: str | None
    timeline: str
    start: int | None  # the window, inclusive (None: the whole run)
    end: int | None
    event_id: str | None
    download: str  # the REST path of a download of exactly the episode's chunks
    missing_why: str | None  # the run is deleted or gone: why


# The columns a segment row is read from (not whole ORM objects: a page holds a thousand runs).
_SEGMENT_COLUMNS = (
    Run.id,
    Run.robot_id,
    Run.status,
    Run.tier,
    Run.started_at,
    Run.ended_at,
    Run.pinned,
    Run.chunks,
    Run.bytes,
    Run.updated_at,
    Run.properties,
)


def _segments(runs: Runs) -> sa.Select[*tuple[Any, ...]]:
    return select(*_SEGMENT_COLUMNS).where(runs).order_by(Run.id)


def segment_rows(session: Session, name: str, after: str | None, limit: int) -> list[SegmentRow]:
    """Up to `limit` segments of dataset `name` with ids after `after`, in id order."""
    query = _segments(application_runs(name)).limit(limit)
    if after is not None:
        query = query.where(Run.id > after)
    return _rows(session, session.execute(query).all())


def segment_rows_named(session: Session, name: str, run_ids: list[str]) -> list[SegmentRow]:
    """The segments of dataset `name` among `run_ids` (other datasets' runs, or none, left out)."""
    run_ids = possible_ids(run_ids)
    return runs_rows(session, application_runs(name), run_ids)


def runs_rows(session: Session, runs: Runs, run_ids: list[str]) -> list[SegmentRow]:
    """The rows of the runs among `run_ids` that `runs` holds, in id order."""
    run_ids = possible_ids(run_ids)
    return _rows(session, session.execute(_segments(runs).where(Run.id.in_(run_ids))).all()) if run_ids else []


def _timelines(session: Session, run_ids: list[str]) -> dict[str, dict[str, tuple[str, int, int]]]:
    """The timelines of runs `run_ids` (in id order). Read by id range, not a list of ids: the
    embedded catalog binds each listed value slowly, and a page's ids are neighbours."""
    found: dict[str, dict[str, tuple[str, int, int]]] = {run_id: {} for run_id in run_ids}
    if not run_ids:
        return found
    query = select(RunTimeline.run_id, RunTimeline.name, RunTimeline.type, RunTimeline.min, RunTimeline.max).where(
        RunTimeline.run_id >= run_ids[0], RunTimeline.run_id <= run_ids[-1]
    )
    for run_id, name, kind, low, high in session.execute(query):
        if run_id in found:  # another dataset's run between two of these
            found[run_id][name] = (kind, low, high)
    return found


def _corpus(
    session: Session, run_ids: list[str]
) -> tuple[dict[str, dict[str, tuple[float | None, str | None]]], dict[str, list[str]]]:
    """The metrics and tags of runs `run_ids` (in id order), read by id range as `_timelines` is."""
    metrics: dict[str, dict[str, tuple[float | None, str | None]]] = {run_id: {} for run_id in run_ids}
    tags: dict[str, list[str]] = {run_id: [] for run_id in run_ids}
    if not run_ids:
        return metrics, tags
    low, high = run_ids[0], run_ids[-1]
    found = select(RunMetric.run_id, RunMetric.name, RunMetric.value, RunMetric.text_value).where(
        RunMetric.run_id >= low, RunMetric.run_id <= high
    )
    for run_id, name, value, text in session.execute(found):
        if run_id in metrics:
            metrics[run_id][name] = (value, text)
    tagged = select(RunTag.run_id, RunTag.tag).where(RunTag.run_id >= low, RunTag.run_id <= high).order_by(RunTag.tag)
    for run_id, tag in session.execute(tagged):
        if run_id in tags:
            tags[run_id].append(tag)
    return metrics, tags


def _rows(session: Session, runs: Sequence[sa.Row[Any]]) -> list[SegmentRow]:
    timelines = _timelines(session, [run.id for run in runs])
    metrics, tags = _corpus(session, [run.id for run in runs])
    return [
        SegmentRow(
            run.id,
            run.robot_id,
            run.status,
            run.tier,
            aware(run.started_at) if run.started_at is not None else None,
            aware(run.ended_at) if run.ended_at is not None else None,
            bool(run.pinned),
            run.chunks,
            run.bytes,
            aware(run.updated_at),
            json_object(run.properties),
            timelines[run.id],
            metrics[run.id],
            tags[run.id],
        )
        for run in runs
    ]


def property_pages(session: Session, runs: str | Runs, page: int) -> Iterator[list[dict[str, Any]]]:
    """The recording properties of every run of `runs` (an application id: its runs), `page` runs at a time."""
    after = ""
    while True:
        query = select(Run.id, Run.properties).where(_runs(runs), Run.id > after).order_by(Run.id).limit(page)
        found = session.execute(query).all()
        if not found:
            return
        yield [json_object(text) for _, text in found]
        after = found[-1][0]


def property_kinds(session: Session, runs: str | Runs, page: int) -> dict[tuple[str, str], set[str]]:
    """Each (property, component) the runs hold (an application id: its runs, as counted in its
    dataset's columns), with the kinds of value they hold in it."""
    if isinstance(runs, str):
        return dataset_columns(session, runs).properties
    kinds: dict[tuple[str, str], set[str]] = {}
    for properties in itertools.chain.from_iterable(property_pages(session, runs, page)):
        for _, name, kind in property_items(properties):
            held = kinds.setdefault(property_key(name), set())
            if kind:
                held.add(kind)
    return kinds


def timeline_types(session: Session, runs: str | Runs) -> dict[str, str]:
    """Each timeline of the runs (an application id: its runs, as counted in its dataset's columns)
    and its type (sequence, timestamp, duration): the type most of them log it with, should runs
    disagree."""
    if isinstance(runs, str):
        return dataset_columns(session, runs).timelines
    query = (
        select(RunTimeline.name, RunTimeline.type, sa.func.count())
        .join(Run, Run.id == RunTimeline.run_id)
        .where(_runs(runs))
        .group_by(RunTimeline.name, RunTimeline.type)
    )
    best: dict[str, tuple[int, str]] = {}
    for name, kind, count in session.execute(query):
        if name not in best or (count, kind) > best[name]:
            best[name] = (count, kind)
    return {name: kind for name, (_, kind) in best.items()}


def metric_kinds(session: Session, runs: str | Runs) -> dict[str, bool]:
    """Each metric some run has (an application id: its runs, as counted in its dataset's columns),
    and whether any run holds it as text."""
    if isinstance(runs, str):
        return dataset_columns(session, runs).metrics
    query = (
        select(RunMetric.name, sa.func.count(RunMetric.text_value))
        .join(Run, Run.id == RunMetric.run_id)
        .where(_runs(runs))
        .group_by(RunMetric.name)
    )
    return {metric: texts > 0 for metric, texts in session.execute(query)}


def property_archetypes(session: Session, runs: str | Runs) -> dict[str, set[str]]:
    """The archetypes logged on each property entity (`/__properties...`) of the runs (an
    application id: its runs, as counted in its dataset's columns)."""
    if isinstance(runs, str):
        return dataset_columns(session, runs).archetypes
    query = (
        select(RunEntity.path, RunEntity.archetypes)
        .join(Run, Run.id == RunEntity.run_id)
        .where(_runs(runs))
        .where(RunEntity.path.startswith(PROPERTIES_ENTITY, autoescape=True))
        .distinct()
    )
    found: dict[str, set[str]] = {}
    for path, archetypes in session.execute(query):
        found.setdefault(path, set()).update(json_names(archetypes))
    return found
