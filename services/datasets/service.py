"""Dataset snapshots as people use them: a selection resolved and written as the next immutable
version of its name, snapshots and their versions listed, one version shown with a page of its
episodes (each saying whether its run is missing now). Each function answers the JSON the REST API
gives; `create` blocks (it reads chunk indexes): callers run it off the event loop."""

from __future__ import annotations

import json
from typing import Any

import sqlalchemy.exc as sa_exc

from catalog import corpus
from catalog import datasets as queries
from catalog.datasets import VersionFacts
from catalog.db import session_scope
from catalog.models import DatasetEpisode, DatasetVersion
from core.clock import aware, iso_utc
from core.cursors import decode_cursor, encode_cursor
from core.errors import BadParameterError, ConflictError, NotFoundError
from services.datasets.resolve import Sources, resolve
from services.datasets.selection import Selection

MAX_LIMIT = 1000
WRITE_TRIES = 3  # another version of the same name written at the same moment: number again


def create(sources: Sources, name: str, selection: Selection, who: str) -> dict[str, Any]:
    """Resolve `selection` and write it as `name`'s next version; its summary."""
    queries.check_name(name)
    selection.check()
    with session_scope(sources.catalog) as session:
        running = corpus.current_rules(session)
        rules_version = running.version if running is not None else None
    resolved = resolve(sources, selection)
    skipped = [{"run": s.run_id, "why": s.why} for s in resolved.skipped]
    facts = VersionFacts(
        selection.to_json(), who, sources.clock(), rules_version, resolved.runs, json.dumps(skipped, sort_keys=True)
    )
    for attempt in range(WRITE_TRIES):
        try:
            with session_scope(sources.catalog, write=True) as session:
                row = queries.add_version(session, name, facts, resolved.episodes)
                return _summary(row, queries.split_counts(session, name, row.version))
        except sa_exc.IntegrityError as exc:  # the same number taken by another writer
            if attempt == WRITE_TRIES - 1:
                raise ConflictError(f"other versions of {name!r} were written at the same moment: try again") from exc
    raise AssertionError("unreachable")


def _summary(row: DatasetVersion, splits: dict[str, dict[str, int]]) -> dict[str, Any]:
    return {
        "name": row.name,
        "version": row.version,
        "ref": queries.ref(row.name, row.version),
        "created_by": row.created_by,
        "created_at": iso_utc(row.created_at),
        "rules_version": row.rules_version,
        "episodes": row.episodes,
        "runs": row.runs,
        "chunks": row.chunks,
        "bytes": row.bytes,
        "splits": {name: counts for name, counts in splits.items() if name},
        "skipped": json.loads(row.skipped),
    }


def datasets_answer(sources: Sources) -> dict[str, Any]:
    """`GET /v1/datasets`: every snapshot with its latest version."""
    with session_scope(sources.catalog) as session:
        return {
            "datasets": [
                {
                    "name": snapshot.name,
                    "created_by": snapshot.created_by,
                    "created_at": iso_utc(snapshot.created_at),
                    "latest": _summary(latest, queries.split_counts(session, latest.name, latest.version))
                    if latest is not None
                    else None,
                }
                for snapshot, latest in queries.snapshots(session)
            ]
        }


def dataset_answer(sources: Sources, name: str) -> dict[str, Any]:
    """`GET /v1/datasets/{name}`: its versions, newest first."""
    with session_scope(sources.catalog) as session:
        found = queries.snapshot(session, name)
        if found is None:
            raise _unknown(name)
        return {
            "name": found.name,
            "created_by": found.created_by,
            "created_at": iso_utc(found.created_at),
            "versions": [
                _summary(v, queries.split_counts(session, name, v.version)) for v in queries.versions(session, name)
            ],
        }


def version_answer(
    sources: Sources, name: str, version: int, limit: int = 100, cursor: str | None = None, chunk_ids: bool = False
) -> dict[str, Any]:
    """`GET /v1/datasets/{name}/{version}`: the version with its selection and a page of episodes
    (with `chunk_ids`, each episode's chunk ids as hex)."""
    if not 1 <= limit <= MAX_LIMIT:
        raise BadParameterError("limit", f"{limit} is not between 1 and {MAX_LIMIT}")
    with session_scope(sources.catalog) as session:
        row = queries.version(session, name, version)
        if row is None:
            if queries.snapshot(session, name) is None:
                raise _unknown(name)
            known = ", ".join(queries.ref(name, v.version) for v in queries.versions(session, name)[:10])
            raise NotFoundError(f"dataset {name!r} has no version {version}: it has {known}")
        after = _after(cursor, row)
        page = queries.episodes(session, name, version, after, limit + 1)
        missing = queries.missing_runs(session, {e.run_id for e in page[:limit]})
        episodes = [_episode(e, missing, chunk_ids) for e in page[:limit]]
        next_cursor = encode_cursor(row.created_at, str(page[limit - 1].episode)) if len(page) > limit else None
        return {
            **_summary(row, queries.split_counts(session, name, version)),
            "selection": json.loads(row.selection),
            "episodes_page": episodes,
            "next_cursor": next_cursor,
        }


def _after(cursor: str | None, row: DatasetVersion) -> int:
    """The episode a cursor says the last page ended at (-1: none); a cursor of another version is refused."""
    if cursor is None:
        return -1
    when, ident = decode_cursor(cursor)
    if when != aware(row.created_at) or not ident.isdigit():
        raise BadParameterError("cursor", "not a cursor of this version: pass `next_cursor` as is")
    return int(ident)


def _episode(episode: DatasetEpisode, missing: dict[str, queries.Missing], chunk_ids: bool) -> dict[str, Any]:
    gone = missing.get(episode.run_id)
    ids = {"chunk_ids": [i.hex() for i in queries.chunk_ids_of(episode)]} if chunk_ids else {}
    return {
        "index": episode.episode,
        "run_id": episode.run_id,
        "robot_id": episode.robot_id,
        "split": episode.split,
        "timeline": episode.timeline,
        "start": episode.range_start,
        "end": episode.range_end,
        "event_id": episode.event_id,
        "chunks": episode.chunks,
        "bytes": episode.bytes,
        "missing": gone is not None,
        "missing_why": gone.why if gone is not None else None,
        **ids,
    }


def _unknown(name: str) -> NotFoundError:
    return NotFoundError(
        f"no dataset {name!r}: see GET /v1/datasets or `fleet datasets ls`; make one with `fleet datasets create`"
    )


def parse_ref(text: str) -> tuple[str, int | None]:
    """`NAME` or `NAME@N` (N None: the latest)."""
    name, sep, number = text.partition("@")
    queries.check_name(name)
    if not sep:
        return name, None
    if not number.isdigit() or not 1 <= int(number) <= 2**63 - 1:
        raise BadParameterError("version", f"{number!r} is not a version number (NAME@1, NAME@2, ...)")
    return name, int(number)
