"""Dataset snapshots in the catalog protocol: each version `NAME@N` of a snapshot (docs/datasets.md)
is a dataset entry of its own, named `NAME:N`, whose segments are its episodes, read from their
runs' chunks.

Why `NAME:N`, not `NAME@N`: Rerun's 0.41 clients refuse an entry name holding `@` (or `~ + / # ,`,
most punctuation, any non-ASCII letter), and refuse the whole FindEntries answer with it, so
`CatalogClient.datasets()` would list nothing. They take letters, digits, `. - _ :`, spaces and
brackets; a snapshot's name holds no `:`, so `NAME:N` names one version.

Entry ids: a TUID made from the version's creation time (as the catalog holds it) and 64 bits of
a digest of its ref, so every node gives a version the same id, for ever, with nothing stored
(`snapshot_entry_id`). An entry id names an application's dataset (the `datasets` table) first,
else the version created at its time whose id it is (`find_dataset`).

Segment ids: a whole-run episode's is its run id (`run-0042`); a window's is the run id, `~` and the
episode's number in the version (`run-0042~3`). A run id never holds `~` (core/ids.py), so each
names one episode and says which run it reads, and both are safe in URLs.

Names: ingest takes any application id the catalog can hold, `:` included, so an application may
be named as a version is. A lookup by name then finds the version (whose name says it is one); the
application's dataset keeps its entry id and is listed beside it.

A version never changes: writes to its entry are refused (FAILED_PRECONDITION) saying so.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from urllib.parse import quote

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import datasets as snapshot_rows
from catalog.models import Dataset, DatasetEpisode, DatasetVersion, Run
from core.clock import aware
from core.errors import ConflictError, NotFoundError
from core.ids import is_id, new_entry_id
from services.redap import datasets
from services.redap.datasets import EpisodeFacts, Runs, SegmentRow
from services.redap.depot import Depot
from services.redap.sources import IndexedRecordingSource, SegmentSource, run_sources
from services.redap.tuid import EPOCH, Tuid, epoch_ns

SEGMENT_SEPARATOR = "~"
NAME_SEPARATOR = ":"  # NAME:N, the entry name of version N (Rerun's clients refuse `@`)
_ENTRY_SALT = "dataset snapshot "  # a version's id is never an application's of the same name and time
_NEAR = dt.timedelta(milliseconds=1)  # a catalog's timestamps are microseconds: looked up around the id's time
_EPISODE_NUMBER = re.compile(r"0|[1-9][0-9]{0,17}")
IDS_PER_QUERY = 500  # segment ids looked up at once


@dataclass(frozen=True)
class SnapshotVersion:
    """A version of a snapshot as an entry of the catalog: its name, number and creation time."""

    name: str
    version: int
    created_at: dt.datetime

    @property
    def ref(self) -> str:
        """`NAME@N`, as the REST API and the CLI name it."""
        return snapshot_rows.ref(self.name, self.version)

    @property
    def entry_name(self) -> str:
        """`NAME:N`, its name in the catalog protocol."""
        return f"{self.name}{NAME_SEPARATOR}{self.version}"

    @property
    def entry_id(self) -> Tuid:
        return snapshot_entry_id(self.name, self.version, self.created_at)

    @property
    def runs(self) -> Runs:
        return datasets.version_runs(self.name, self.version)

    def immutable(self, what: str) -> ConflictError:
        return ConflictError(
            f"{self.entry_name} ({self.ref}) is a dataset snapshot version, which never changes: {what} is refused. "
            f"Make a new version with `fleet datasets create {self.name}` (POST /v1/datasets)"
        )


def snapshot_entry_id(name: str, version: int, created_at: dt.datetime) -> Tuid:
    return Tuid.parse(new_entry_id(_ENTRY_SALT + snapshot_rows.ref(name, version), epoch_ns(created_at)))


_VERSION_COLUMNS = (DatasetVersion.name, DatasetVersion.version, DatasetVersion.created_at)


def snapshot_versions(session: Session) -> list[SnapshotVersion]:
    """Every version of every snapshot, by name and number."""
    query = sa.select(*_VERSION_COLUMNS).order_by(DatasetVersion.name, DatasetVersion.version)
    return [SnapshotVersion(name, number, aware(at)) for name, number, at in session.execute(query)]


def snapshot_by_entry(session: Session, entry: Tuid) -> SnapshotVersion | None:
    """The version whose entry id this is, if any: among those created at its time."""
    try:
        moment = EPOCH + dt.timedelta(microseconds=entry.time_ns // 1000)
        low, high = moment - _NEAR, moment + _NEAR
    except OverflowError:  # no version was made in the year 10000
        return None
    query = sa.select(*_VERSION_COLUMNS).where(DatasetVersion.created_at >= low, DatasetVersion.created_at <= high)
    for name, number, at in session.execute(query):
        found = SnapshotVersion(name, number, aware(at))
        if found.entry_id == entry:
            return found
    return None


def find_dataset(session: Session, entry: Tuid) -> Dataset | SnapshotVersion:
    """The dataset an `x-rerun-entry-id` names: an application's, else a snapshot version's;
    NOT_FOUND naming how to list them."""
    found = session.scalars(sa.select(Dataset).where(Dataset.entry_id == str(entry))).first()
    if found is not None:
        return found
    version = snapshot_by_entry(session, entry)
    if version is None:
        raise NotFoundError(f"no dataset has entry id {entry}: list the catalog's entries (FindEntries) for their ids")
    return version


# --- segments: the episodes ---------------------------------------------------------------------


def segment_id_of(episode: DatasetEpisode) -> str:
    """`RUN` for a whole-run episode, `RUN~N` for episode N, a window of run RUN."""
    if episode.range_start is None and episode.range_end is None:
        return episode.run_id
    return f"{episode.run_id}{SEGMENT_SEPARATOR}{episode.episode}"


def _parse_segment(segment_id: str) -> tuple[str, int | None] | None:
    """(run id, episode number or None) of a segment id of that form; None for any other string."""
    run_id, separator, number = segment_id.partition(SEGMENT_SEPARATOR)
    if not is_id(run_id):
        return None
    if not separator:
        return run_id, None
    return (run_id, int(number)) if _EPISODE_NUMBER.fullmatch(number) else None


def _version_episodes(version: SnapshotVersion) -> sa.Select[DatasetEpisode]:
    return sa.select(DatasetEpisode).where(
        DatasetEpisode.name == version.name, DatasetEpisode.version == version.version
    )


def episodes_named(session: Session, version: SnapshotVersion, segment_ids: Iterable[str]) -> list[DatasetEpisode]:
    """The version's episodes these segment ids name, in episode order (an id naming none: left out)."""
    wanted = set(segment_ids)
    parsed = [found for found in map(_parse_segment, sorted(wanted)) if found is not None]
    runs = sorted({run_id for run_id, number in parsed if number is None})
    numbers = sorted({number for _, number in parsed if number is not None})
    found: dict[int, DatasetEpisode] = {}
    for column, values in ((DatasetEpisode.run_id, runs), (DatasetEpisode.episode, numbers)):
        for start in range(0, len(values), IDS_PER_QUERY):
            batch = values[start : start + IDS_PER_QUERY]
            found.update((e.episode, e) for e in session.scalars(_version_episodes(version).where(column.in_(batch))))
    return sorted((e for e in found.values() if segment_id_of(e) in wanted), key=lambda e: e.episode)


def episode_page(session: Session, version: SnapshotVersion, after: int, limit: int) -> list[DatasetEpisode]:
    """Up to `limit` of the version's episodes numbered above `after` (-1: from the first), in order."""
    return snapshot_rows.episodes(session, version.name, version.version, after, limit)


def episode_of(session: Session, version: SnapshotVersion, segment_id: str) -> DatasetEpisode:
    """The episode a segment id names; NOT_FOUND saying what the version's segment ids are."""
    found = episodes_named(session, version, [segment_id])
    if not found:
        raise NotFoundError(
            f"dataset {version.entry_name!r} has no segment {segment_id!r}: its segments are its episodes, "
            f"RUN for a whole run, RUN{SEGMENT_SEPARATOR}N for episode N, a window of run RUN (see its segment table)"
        )
    return found[0]


def missing_why(session: Session, version: SnapshotVersion, episode: DatasetEpisode) -> str | None:
    """Why the episode's run cannot be read any more (deleted, gone from the catalog), or None."""
    found = snapshot_rows.missing_runs(session, [episode.run_id]).get(episode.run_id)
    return None if found is None else _missing(version, episode, found.why)


def _missing(version: SnapshotVersion, episode: DatasetEpisode, why: str) -> str:
    return (
        f"segment {segment_id_of(episode)!r} of {version.entry_name} reads run {episode.run_id!r}, "
        f"which is missing: {why} (the snapshot keeps the episode, not the run's data)"
    )


# --- the segment table's rows -------------------------------------------------------------------


def episode_rows(session: Session, version: SnapshotVersion, episodes: Sequence[DatasetEpisode]) -> list[SegmentRow]:
    """The segment table's rows of these episodes: each its run's facts (none for a run gone from
    the catalog), the episode's chunks and bytes, its window on its timeline's columns, and its facts."""
    run_ids = sorted({e.run_id for e in episodes})
    runs = {row.run_id: row for row in datasets.runs_rows(session, version.runs, run_ids)}
    missing = snapshot_rows.missing_runs(session, run_ids)
    rows = []
    for episode in episodes:
        gone = missing.get(episode.run_id)
        facts = EpisodeFacts(
            segment_id_of(episode),
            episode.episode,
            episode.split,
            episode.timeline,
            episode.range_start,
            episode.range_end,
            episode.event_id,
            _download(version, episode),
            _missing(version, episode, gone.why) if gone is not None else None,
        )
        run = runs.get(episode.run_id) or SegmentRow(
            episode.run_id, episode.robot_id, "", "deleted", None, None, False, 0, 0, version.created_at, {}, {}
        )
        rows.append(
            replace(
                run,
                chunks=episode.chunks,
                bytes=episode.bytes,
                updated_at=version.created_at,  # a version never changes
                timelines=_in_window(run.timelines, episode),
                episode=facts,
            )
        )
    return rows


def _download(version: SnapshotVersion, episode: DatasetEpisode) -> str:
    """The REST download of exactly the episode's chunks."""
    name = quote(version.name, safe="")
    return f"/v1/datasets/{name}/{version.version}/episodes/{episode.episode}/recording.rrd"


def _in_window(timelines: dict[str, tuple[str, int, int]], episode: DatasetEpisode) -> dict[str, tuple[str, int, int]]:
    """The run's timeline ranges, the episode's own timeline cut to its window: what a reader of the
    episode samples (its chunks also hold the scene before the window, the latest-at data)."""
    start, end = episode.range_start, episode.range_end
    found = timelines.get(episode.timeline)
    if start is None or end is None or found is None:
        return timelines
    kind, low, high = found
    low, high = (max(low, start), min(high, end)) if max(low, start) <= min(high, end) else (start, end)
    return {**timelines, episode.timeline: (kind, low, high)}


# --- what queries read --------------------------------------------------------------------------


def episode_sources(
    depot: Depot, session: Session, version: SnapshotVersion, only: frozenset[str] | None
) -> list[SegmentSource]:
    """The version's episodes (`only` those named), each with its run's recording and its chunk
    ids; an episode whose run is missing cannot be read (NOT_FOUND saying why)."""
    everything = 2**62
    named = episodes_named(session, version, only) if only is not None else None
    episodes = named if named is not None else episode_page(session, version, -1, everything)
    run_ids = sorted({e.run_id for e in episodes})
    missing = snapshot_rows.missing_runs(session, run_ids)
    readable = [run_id for run_id in run_ids if run_id not in missing]
    runs: list[Run] = []
    for start in range(0, len(readable), IDS_PER_QUERY):
        batch = readable[start : start + IDS_PER_QUERY]
        runs += session.scalars(sa.select(Run).where(Run.id.in_(batch)))
    sources = {s.run_id: s for s in run_sources(depot, session, sorted(runs, key=lambda r: r.id), depot.clock())}
    found = []
    for episode in episodes:
        gone = missing.get(episode.run_id)
        source = (
            IndexedRecordingSource(episode.run_id, unreadable=NotFoundError(_missing(version, episode, gone.why)))
            if gone is not None
            else sources[episode.run_id]
        )
        found.append(SegmentSource(segment_id_of(episode), source, frozenset(snapshot_rows.chunk_ids_of(episode))))
    return found
