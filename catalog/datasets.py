"""Catalog reads and writes of dataset snapshots: named snapshots, their immutable versions
(`NAME@N`) and each version's episodes, and which snapshots use given runs (what retention asks
before it deletes one).

A version is written whole in one transaction and never changed after; a new resolution of NAME is
NAME@(the highest + 1). Two writers of the same name at once: one of them fails on the version's
primary key and tries again (`services.datasets.service`).
"""

from __future__ import annotations

import datetime as dt
import re
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import DatasetEpisode, DatasetSnapshot, DatasetVersion, Event, Run, RunLifecycle
from catalog.queries import insert_rows
from core.errors import BadParameterError
from core.states import Tier

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
CHUNK_ID_BYTES = 16
RUNS_PER_QUERY = 500  # run ids asked about at once (an IN list of bounded length)


def check_name(name: str) -> str:
    """A snapshot's name as the catalog holds it, else a 422 naming `name`."""
    if not NAME.fullmatch(name):
        shown = name if len(name) <= 80 else name[:80] + "..."
        raise BadParameterError(
            "name", f"{shown!r}: 1 to 64 characters from A-Z a-z 0-9 . _ -, starting with a letter or digit"
        )
    return name


def ref(name: str, version: int) -> str:
    """How a version is named: `NAME@N`."""
    return f"{name}@{version}"


@dataclass(frozen=True)
class EpisodeRecord:
    """An episode as resolved: a run, whole (`range_start` and `range_end` None) or a window on
    `timeline` around an event, and the chunks it reads (sorted ids, their frames' bytes)."""

    run_id: str
    robot_id: str
    split: str | None
    timeline: str
    range_start: int | None
    range_end: int | None
    event_id: str | None
    chunk_ids: tuple[bytes, ...]
    bytes: int


@dataclass(frozen=True)
class VersionFacts:
    """What a version records besides its episodes."""

    selection: str  # canonical JSON
    created_by: str
    created_at: dt.datetime
    rules_version: int | None
    runs: int
    skipped: str  # JSON


def add_version(session: Session, name: str, facts: VersionFacts, episodes: Sequence[EpisodeRecord]) -> DatasetVersion:
    """Write `name`'s next version with its episodes (the snapshot made on its first version)."""
    if session.get(DatasetSnapshot, name) is None:
        session.add(DatasetSnapshot(name=name, created_by=facts.created_by, created_at=facts.created_at))
    highest = session.scalar(sa.select(sa.func.max(DatasetVersion.version)).where(DatasetVersion.name == name))
    number = (highest or 0) + 1
    row = DatasetVersion(
        name=name,
        version=number,
        selection=facts.selection,
        created_by=facts.created_by,
        created_at=facts.created_at,
        rules_version=facts.rules_version,
        episodes=len(episodes),
        runs=facts.runs,
        chunks=sum(len(e.chunk_ids) for e in episodes),
        bytes=sum(e.bytes for e in episodes),
        skipped=facts.skipped,
    )
    session.add(row)
    session.flush()  # the version's key first: a writer that lost the race fails here, before its episodes
    insert_rows(session, DatasetEpisode, [_episode_row(name, number, i, e) for i, e in enumerate(episodes)])
    return row


def _episode_row(name: str, version: int, index: int, episode: EpisodeRecord) -> dict[str, object]:
    return {
        "name": name,
        "version": version,
        "episode": index,
        "run_id": episode.run_id,
        "robot_id": episode.robot_id,
        "split": episode.split,
        "timeline": episode.timeline,
        "range_start": episode.range_start,
        "range_end": episode.range_end,
        "event_id": episode.event_id,
        "chunk_ids": b"".join(sorted(episode.chunk_ids)),
        "chunks": len(episode.chunk_ids),
        "bytes": episode.bytes,
    }


def chunk_ids_of(episode: DatasetEpisode) -> list[bytes]:
    """The episode's chunk ids, in order."""
    data = episode.chunk_ids
    return [data[i : i + CHUNK_ID_BYTES] for i in range(0, len(data), CHUNK_ID_BYTES)]


def window_events(session: Session, run_id: str, kinds: Sequence[str]) -> list[Event]:
    """The run's events of these kinds, in timeline order (what a snapshot puts windows around)."""
    query = (
        sa.select(Event)
        .where(Event.run_id == run_id, Event.kind.in_(list(kinds)))
        .order_by(Event.range_start, Event.range_end, Event.id)
    )
    return list(session.scalars(query))


def snapshots(session: Session) -> list[tuple[DatasetSnapshot, DatasetVersion | None]]:
    """Every snapshot by name, with its latest version."""
    latest = (
        sa.select(DatasetVersion.name, sa.func.max(DatasetVersion.version).label("version"))
        .group_by(DatasetVersion.name)
        .subquery()
    )
    query = (
        sa.select(DatasetSnapshot, DatasetVersion)
        .outerjoin(latest, latest.c.name == DatasetSnapshot.name)
        .outerjoin(
            DatasetVersion, sa.and_(DatasetVersion.name == latest.c.name, DatasetVersion.version == latest.c.version)
        )
        .order_by(DatasetSnapshot.name)
    )
    return [(snapshot, version) for snapshot, version in session.execute(query).all()]


def snapshot(session: Session, name: str) -> DatasetSnapshot | None:
    return session.get(DatasetSnapshot, name)


def versions(session: Session, name: str) -> list[DatasetVersion]:
    """A snapshot's versions, newest first."""
    query = sa.select(DatasetVersion).where(DatasetVersion.name == name).order_by(DatasetVersion.version.desc())
    return list(session.scalars(query))


def version(session: Session, name: str, number: int) -> DatasetVersion | None:
    return session.get(DatasetVersion, (name, number))


def episodes(session: Session, name: str, number: int, after: int, limit: int) -> list[DatasetEpisode]:
    """A page of a version's episodes in order: those numbered above `after` (-1: from the first)."""
    query = (
        sa.select(DatasetEpisode)
        .where(DatasetEpisode.name == name, DatasetEpisode.version == number, DatasetEpisode.episode > after)
        .order_by(DatasetEpisode.episode)
        .limit(limit)
    )
    return list(session.scalars(query))


def split_counts(session: Session, name: str, number: int) -> dict[str, dict[str, int]]:
    """Per split (`""`: none given), how many runs and episodes a version has in it."""
    query = (
        sa.select(
            DatasetEpisode.split,
            sa.func.count(sa.distinct(DatasetEpisode.run_id)),
            sa.func.count(),
            sa.func.sum(DatasetEpisode.chunks),
        )
        .where(DatasetEpisode.name == name, DatasetEpisode.version == number)
        .group_by(DatasetEpisode.split)
    )
    return {
        split or "": {"runs": int(runs), "episodes": int(count), "chunks": int(chunks or 0)}
        for split, runs, count, chunks in session.execute(query).all()
    }


@dataclass(frozen=True)
class Missing:
    """Why a run an episode reads is not in the catalog to be read any more."""

    run_id: str
    why: str


def missing_runs(session: Session, run_ids: Iterable[str]) -> dict[str, Missing]:
    """Of `run_ids`, those deleted since (a tombstone) or gone from the catalog, each with why."""
    wanted = sorted(set(run_ids))
    found: dict[str, tuple[str, dt.datetime | None, str | None]] = {}
    for start in range(0, len(wanted), RUNS_PER_QUERY):
        batch = wanted[start : start + RUNS_PER_QUERY]
        query = (
            sa.select(Run.id, Run.tier, RunLifecycle.deleted_at, RunLifecycle.deleted_by)
            .outerjoin(RunLifecycle, RunLifecycle.run_id == Run.id)
            .where(Run.id.in_(batch))
        )
        found.update((run_id, (tier, at, by)) for run_id, tier, at, by in session.execute(query).all())
    out = {}
    for run_id in wanted:
        if run_id not in found:
            out[run_id] = Missing(run_id, "the catalog no longer has this run")
            continue
        tier, at, by = found[run_id]
        if tier == Tier.DELETED:
            when = at.strftime("%Y-%m-%d %H:%M UTC") if at is not None else "an unknown time"
            out[run_id] = Missing(run_id, f"run deleted on {when} by {by or 'someone'}")
    return out


def snapshots_using(session: Session, run_ids: Iterable[str]) -> dict[str, list[str]]:
    """Of `run_ids`, those some snapshot version lists, each with the versions (`NAME@N`, sorted)."""
    wanted = sorted(set(run_ids))
    used: dict[str, set[tuple[str, int]]] = defaultdict(set)
    for start in range(0, len(wanted), RUNS_PER_QUERY):
        batch = wanted[start : start + RUNS_PER_QUERY]
        query = (
            sa.select(DatasetEpisode.run_id, DatasetEpisode.name, DatasetEpisode.version)
            .where(DatasetEpisode.run_id.in_(batch))
            .distinct()
        )
        for run_id, name, number in session.execute(query).all():
            used[run_id].add((name, number))
    return {run_id: [ref(name, number) for name, number in sorted(refs)] for run_id, refs in used.items()}


def describe_use(refs: Sequence[str], most: int = 5) -> str:
    """`dataset a@1, b@2` (the first `most`, and how many more)."""
    shown = ", ".join(refs[:most])
    more = f" and {len(refs) - most} more" if len(refs) > most else ""
    return f"dataset{'s' if len(refs) > 1 else ''} {shown}{more}"
