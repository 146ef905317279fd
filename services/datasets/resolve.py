"""A selection resolved into episodes: the runs it matches (paged through `list_runs`, up to a cap),
for each one episode (the whole run) or one per event of the window's kinds, and for each episode
the chunk ids it reads, chosen from the run's chunk index (hot on this node, or sealed) as a
windowed download chooses them: the recording's chunks of the entities asked for that overlap the
window, the static ones, and per entity and component the latest-at candidates before the window's
start (`services.runs.latest_at`). Runs that cannot be read now (cold and not restored, deleted, hot
on another node) are skipped, each with why.

Blocking work (catalog queries, chunk index reads, ranged reads): callers run it off the event loop.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from catalog import datasets as queries
from catalog.datasets import EpisodeRecord
from catalog.db import session_scope
from catalog.models import Event
from core.errors import BadParameterError, FleetError
from core.states import Tier
from services.datasets.selection import Selection
from services.edge.triggers import steps
from services.hot.read import HotRuns
from services.rrd.chunk_index import CHUNK, IndexRow
from services.runs.download import EntityFilter, TimeWindow
from services.runs.indexed import IndexedRecording, open_hot, plan_window
from services.runs.sealed import indexed_recording
from services.runs.service import list_runs
from services.sealed.read import locate_sealed
from services.storage.objectstore import ObjectStore

MAX_RUNS = 10_000  # runs a selection may match: a snapshot of more is several snapshots
PAGE = 1000
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


@dataclass(frozen=True)
class Sources:
    """Where runs are read from: the catalog, this node's hot runs (None: a node without ingest),
    the warm store, the clock (a restored cold run is readable until its restore ends)."""

    catalog: sessionmaker[Session]
    warm: ObjectStore
    hot_runs: HotRuns | None
    clock: Callable[[], dt.datetime]


@dataclass(frozen=True)
class RunRef:
    id: str
    robot_id: str
    tier: str


@dataclass(frozen=True)
class Skipped:
    run_id: str
    why: str


@dataclass(frozen=True)
class Resolved:
    episodes: list[EpisodeRecord]
    skipped: list[Skipped]
    runs: int  # distinct runs with an episode


def resolve(sources: Sources, selection: Selection) -> Resolved:
    """The episodes of a checked selection, in run id order (and within a run, event order)."""
    entities = EntityFilter(list(selection.include), list(selection.exclude))
    episodes: list[EpisodeRecord] = []
    skipped: list[Skipped] = []
    for run in matching_runs(sources.catalog, selection):
        found = run_episodes(sources, selection, entities, run)
        if isinstance(found, Skipped):
            skipped.append(found)
        else:
            episodes += found
    return Resolved(episodes, skipped, len({e.run_id for e in episodes}))


def matching_runs(catalog: sessionmaker[Session], selection: Selection) -> list[RunRef]:
    """Every run the selection's filters match, paged through `list_runs` in id order; a 422 past
    MAX_RUNS."""
    found: list[RunRef] = []
    cursor: str | None = None
    while True:
        with session_scope(catalog) as session:
            page, cursor = list_runs(session, selection.run_filter(limit=PAGE, cursor=cursor))
            found += [RunRef(run.id, run.robot_id, run.tier) for run in page]
        if len(found) > MAX_RUNS:
            raise BadParameterError(
                "selection",
                f"it matches more than {MAX_RUNS:,} runs: narrow it (robot, since, until, tag, event, ...) "
                "or make several snapshots",
            )
        if cursor is None:
            return found


def run_episodes(
    sources: Sources, selection: Selection, entities: EntityFilter, run: RunRef
) -> list[EpisodeRecord] | Skipped:
    """The run's episodes (none: no event of the window's kinds), or why it was skipped."""
    events: list[Event] = []
    if selection.event_window is not None:
        with session_scope(sources.catalog) as session:
            events = queries.window_events(session, run.id, selection.event_window.event)
            session.expunge_all()
        if not events:
            return []
    opened = open_run(sources, run)
    if isinstance(opened, Skipped):
        return opened
    try:
        rows = list(opened.index())
        if selection.event_window is None:
            return [_episode(run, selection, rows, entities, None, None)]
        return [_episode(run, selection, rows, entities, event, opened) for event in events]
    except FleetError as exc:  # a hot run sealed while it was read, an object gone meanwhile
        return Skipped(run.id, str(exc))
    finally:
        opened.close()


def open_run(sources: Sources, run: RunRef) -> IndexedRecording | Skipped:
    """The run's recording with its chunk index: hot on this node, else sealed (warm, or cold once
    restored), else why not."""
    if run.tier == Tier.DELETED:
        return Skipped(run.id, "deleted")
    hot = sources.hot_runs.hot_recording(run.id) if sources.hot_runs is not None else None
    if hot is not None:
        return open_hot(hot)
    try:
        return indexed_recording(locate_sealed(sources.catalog, sources.warm, run.id, sources.clock()))
    except FleetError as exc:
        if run.tier == Tier.HOT:
            return Skipped(run.id, "hot on another node: make the snapshot on its node, or once it is sealed")
        return Skipped(run.id, str(exc))  # cold and not restored (how to restore it), deleted meanwhile


def _episode(
    run: RunRef,
    selection: Selection,
    rows: list[IndexRow],
    entities: EntityFilter,
    event: Event | None,
    recording: IndexedRecording | None,
) -> EpisodeRecord:
    lengths = {
        r.chunk_id: r.length
        for r in rows
        if r.kind == CHUNK and r.store_kind == "recording" and r.chunk_id and entities(r.entity_path or "")
    }
    split = split_of(selection.seed, run.id, selection.split)
    if event is None or recording is None:
        ids = sorted(lengths)
        return EpisodeRecord(
            run.id, run.robot_id, split, selection.timeline, None, None, None, tuple(ids), sum(lengths.values())
        )
    window = event_window(selection, event)
    keep, _ = plan_window(recording, rows, entities, window)
    ids = sorted(keep & lengths.keys())
    return EpisodeRecord(
        run.id,
        run.robot_id,
        split,
        window.timeline,
        window.start,
        window.end,
        event.id,
        tuple(ids),
        sum(lengths[i] for i in ids),
    )


def event_window(selection: Selection, event: Event) -> TimeWindow:
    """[start - before, end + after] on the event's timeline, latest-at candidates included."""
    assert selection.event_window is not None
    before = steps(selection.event_window.before_s, event.timeline_type)
    after = steps(selection.event_window.after_s, event.timeline_type)
    start = max(INT64_MIN, event.range_start - before)
    end = min(INT64_MAX, event.range_end + after)
    return TimeWindow(event.timeline, start, end, latest_at=True)


def split_of(seed: int, run_id: str, split: Sequence[tuple[str, float]]) -> str | None:
    """The split a run is in: a hash of (seed, run id) as a number in [0, 1), bucketed by the
    cumulative fractions in the order given (the last split takes what rounding leaves)."""
    if not split:
        return None
    digest = hashlib.sha256(f"{seed}\x00{run_id}".encode()).digest()
    point = int.from_bytes(digest[:8], "big") / 2**64
    total = 0.0
    for name, fraction in split:
        total += fraction
        if point < total:
            return name
    return split[-1][0]
