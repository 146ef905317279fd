"""A snapshot version's episodes read from the depot: its episodes in order (paged from the
catalog), each opened on its run (hot on this node, or sealed) with the index rows of the chunks it
lists; the export of a version into a folder (`export_version`), and one episode's chunks as an RRD
stream (`episode_recording`, what the command line exports from)."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from catalog import datasets as queries
from catalog import queries as run_queries
from catalog.db import session_scope
from catalog.models import DatasetEpisode
from core.errors import ConflictError, NotFoundError
from services.datasets.export import (
    EpisodeInfo,
    ExportResult,
    ExportSpec,
    OpenedEpisode,
    OpenEpisode,
    Progress,
    Unreadable,
    export_episodes,
)
from services.datasets.quality import Limits
from services.datasets.resolve import RunRef, Skipped, Sources, open_run
from services.rrd.chunk_index import IndexRow
from services.runs.download import EntityFilter, encode_run
from services.runs.indexed import IndexedRecording, choose_rows, read_events

PAGE = 500  # episodes read from the catalog at once


def version_row(sources: Sources, name: str, version: int) -> tuple[int, str]:
    """The version's episode count and selection; 404 naming how to list versions."""
    with session_scope(sources.catalog) as session:
        row = queries.version(session, name, version)
        if row is None:
            raise NotFoundError(f"no dataset version {queries.ref(name, version)}: `fleet datasets show {name}`")
        return row.episodes, row.selection


def version_episodes(sources: Sources, name: str, version: int) -> Iterator[EpisodeInfo]:
    after = -1
    while True:
        with session_scope(sources.catalog) as session:
            page = queries.episodes(session, name, version, after, PAGE)
            infos = [EpisodeInfo(e.episode, e.run_id, e.timeline, e.range_start, e.range_end) for e in page]
        yield from infos
        if len(page) < PAGE:
            return
        after = infos[-1].episode


@dataclass(frozen=True)
class _Located:
    """Where an episode's chunks are: its run, the chunk ids it lists, the run's properties."""

    run: RunRef
    wanted: set[bytes]
    properties: dict[str, Any]


def _locate(sources: Sources, name: str, version: int, episode: int) -> _Located:
    with session_scope(sources.catalog) as session:
        row = session.get(DatasetEpisode, (name, version, episode))
        if row is None:
            raise NotFoundError(
                f"{queries.ref(name, version)} has no episode {episode}: `fleet datasets show {name}@{version}`"
            )
        run = run_queries.get_run(session, row.run_id)
        tier = run.tier if run is not None else "deleted"
        properties = json.loads(run.properties or "{}") if run is not None else {}
        return _Located(RunRef(row.run_id, row.robot_id, tier), set(queries.chunk_ids_of(row)), properties)


def episode_opener(sources: Sources, name: str, version: int) -> OpenEpisode:
    @contextmanager
    def open_episode(info: EpisodeInfo) -> Iterator[OpenedEpisode]:
        located = _locate(sources, name, version, info.episode)
        opened = open_run(sources, located.run)
        if isinstance(opened, Skipped):
            raise Unreadable(f"its run {info.run_id} cannot be read: {opened.why}")
        try:
            rows = [r for r in opened.index() if r.chunk_id in located.wanted]
            yield OpenedEpisode(opened, rows, hot=opened.hot is not None, properties=located.properties)
        finally:
            opened.close()

    return open_episode


def export_version(
    sources: Sources,
    name: str,
    version: int,
    spec: ExportSpec,
    root: Path | None,
    progress: Callable[[Progress], None] | None = None,
    limits: Limits | None = None,
) -> ExportResult:
    """NAME@VERSION written under `root` (resuming an export there), or checked (`root` None)."""
    total, _ = version_row(sources, name, version)
    return export_episodes(
        version_episodes(sources, name, version),
        total,
        episode_opener(sources, name, version),
        spec,
        root,
        limits=limits,
        progress=progress,
    )


def episode_recording(sources: Sources, name: str, version: int, episode: int) -> Iterator[bytes | memoryview]:
    """The chunks an episode reads, as one RRD stream (its run's recording info first): exactly the
    snapshot's chunks, whatever the run holds now. Opened before the first piece is asked for, so a
    missing episode or an unreadable run is an error, not a broken stream."""
    located = _locate(sources, name, version, episode)
    ref, wanted = located.run, located.wanted
    opened = open_run(sources, ref)
    if isinstance(opened, Skipped):
        raise ConflictError(f"episode {episode} reads run {ref.id}, which cannot be read now: {opened.why}")
    try:
        rows = list(opened.index())
    except BaseException:
        opened.close()
        raise
    return _streamed(opened, rows, wanted)


def _streamed(opened: IndexedRecording, rows: list[IndexRow], wanted: set[bytes]) -> Iterator[bytes | memoryview]:
    try:
        every = EntityFilter([], [])
        chosen = choose_rows(rows, every, False, wanted)
        yield from encode_run(
            read_events(opened, chosen),
            every,
            blueprint=False,
            window=None,
            keep=wanted,
            picks={},
            metas=opened.metas,
        )
    finally:
        opened.close()
