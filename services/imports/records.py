"""Imports as the catalog keeps them: one row per upload, added as it starts and updated as it goes,
the answers `GET /v1/imports` gives, and the quarantine of failed MCAP originals in the warm store
(`quarantine/imports/ID/NAME`), kept `FLEET_IMPORT_QUARANTINE_DAYS` for an admin and for a retry.

Bookkeeping of an RRD upload is best effort: a catalog that does not answer must not stop an upload
(the data path keeps working through catalog outages), so its row may then be missing or stale.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog import imports as rows
from catalog.db import session_scope
from catalog.models import Import
from core.clock import iso_utc
from core.errors import BadParameterError, NotFoundError
from services.node import Node
from services.storage.objectstore import ObjectStore

log = logging.getLogger(__name__)

QUARANTINE_PREFIX = "quarantine/imports/"
MAX_LIMIT = 500


@dataclass(frozen=True)
class Ledger:
    """Where imports are written: the catalog, the warm store (quarantine), this node, the clock."""

    catalog: sessionmaker[Session]
    warm: ObjectStore
    node_id: str
    clock: Any  # () -> datetime
    quarantine_days: float

    @classmethod
    def of(cls, node: Node) -> Ledger:
        settings = node.settings
        return cls(node.catalog, node.tiers.warm, settings.node_id, node.clock, settings.import_quarantine_days)

    def start(self, kind: str, name: str, who: str, robot: str | None, **values: Any) -> str:
        """A new import, receiving; its id."""
        now = self.clock()
        row = Import(
            id="imp-" + secrets.token_hex(6),
            kind=kind,
            state=rows.RECEIVING,
            name=name[:256],
            bytes=0,
            robot_id=robot,
            run_ids="[]",
            chunks_new=0,
            chunks_duplicate=0,
            node=self.node_id,
            created_by=who[:256],
            created_at=now,
            updated_at=now,
            **values,
        )
        with session_scope(self.catalog, write=True) as session:
            return rows.add(session, row).id

    def update(self, import_id: str, **values: Any) -> None:
        with session_scope(self.catalog, write=True) as session:
            rows.update(session, import_id, self.clock(), **values)

    def filed(self, import_id: str, received: int, report: dict[str, Any], **values: Any) -> None:
        """The import filed; `report` is the ingest report (this node's, or the run owner's)."""
        self.update(import_id, state=rows.FILED, bytes=received, **_counts(report), **values)

    def failed(self, import_id: str, received: int, reason: str, report: dict[str, Any] | None = None) -> None:
        """The import failed, and why; `report`: what was kept of it before the failure, if anything."""
        counts = _counts(report) if report else {}
        self.update(import_id, state=rows.FAILED, bytes=received, reason=reason[:2000], **counts)

    def quarantine(self, import_id: str, original: Path, name: str) -> None:
        """Keep a failed import's original for an admin and a retry."""
        key = f"{QUARANTINE_PREFIX}{import_id}/{safe_name(name)}"
        with open(original, "rb") as f:
            self.warm.put(key, f)
        until = self.clock() + dt.timedelta(days=self.quarantine_days)
        self.update(import_id, quarantine_key=key, quarantine_until=until)

    def row(self, import_id: str) -> Import:
        with session_scope(self.catalog) as session:
            found = rows.get(session, import_id)
            if found is None:
                raise NotFoundError(f"no import {import_id[:64]!r}: `fleet imports ls` lists them")
            session.expunge(found)
            return found


def run_ids_of(row: Import) -> list[str]:
    """The runs an import filed into (a JSON list in its row)."""
    return [str(r) for r in json.loads(row.run_ids)]


def _counts(report: dict[str, Any]) -> dict[str, Any]:
    return {
        "run_ids": json.dumps(sorted(str(r) for r in report.get("runs") or [])),
        "chunks_new": int(report.get("chunks_new") or 0),
        "chunks_duplicate": int(report.get("chunks_duplicate") or 0),
    }


def safe_name(name: str) -> str:
    """A client's file name as the last part of an object key: letters, digits, `._-` only."""
    kept = "".join(c if c.isalnum() or c in "._-" else "_" for c in Path(name).name)[:120].lstrip(".")
    return kept or "original.mcap"


def import_json(row: Import) -> dict[str, Any]:
    return {
        "id": row.id,
        "kind": row.kind,
        "state": row.state,
        "name": row.name,
        "bytes": row.bytes,
        "robot": row.robot_id,
        "runs": run_ids_of(row),
        "application": row.application_id,
        "chunks_new": row.chunks_new,
        "chunks_duplicate": row.chunks_duplicate,
        "reason": row.reason,
        "digest": row.digest,
        "held_by": row.held_by,
        "converter": row.converter,
        "quarantined": row.quarantine_key is not None,
        "quarantine_until": iso_utc(row.quarantine_until) if row.quarantine_until else None,
        "created_by": row.created_by,
        "created_at": iso_utc(row.created_at),
        "updated_at": iso_utc(row.updated_at),
    }


def listed(
    catalog: sessionmaker[Session],
    *,
    state: str | None,
    kind: str | None,
    robot: str | None,
    limit: int,
    before: str | None,
) -> dict[str, Any]:
    if state is not None and state not in rows.STATES:
        raise BadParameterError("state", f"{state[:40]!r}: one of {', '.join(rows.STATES)}")
    if kind is not None and kind not in rows.KINDS:
        raise BadParameterError("kind", f"{kind[:40]!r}: one of {', '.join(rows.KINDS)}")
    if not 1 <= limit <= MAX_LIMIT:
        raise BadParameterError("limit", f"{limit}: 1 to {MAX_LIMIT}")
    with session_scope(catalog) as session:
        found = rows.listed(session, state=state, kind=kind, robot=robot, limit=limit, before=before)
        answer: dict[str, Any] = {"imports": [import_json(r) for r in found]}
        if len(found) == limit:
            answer["next_before"] = found[-1].id
        return answer


def purge_quarantine(catalog: sessionmaker[Session], warm: ObjectStore, now: dt.datetime) -> int:
    """Delete the originals whose time in quarantine is over; how many (a job of the schedule)."""
    with session_scope(catalog) as session:
        due = [(r.id, r.quarantine_key) for r in rows.quarantine_expired(session, now)]
    for import_id, key in due:
        if key:
            warm.delete(key)
        with session_scope(catalog, write=True) as session:
            rows.update(session, import_id, now, quarantine_key=None, quarantine_until=None)
    if due:
        log.info("deleted %d quarantined import originals whose time was over", len(due))
    return len(due)


def quarantined(ledger: Ledger, import_id: str) -> tuple[str, int, str]:
    """A failed import's original in quarantine: its key, size and a file name for it."""
    row = ledger.row(import_id)
    if not row.quarantine_key:
        raise NotFoundError(
            f"import {import_id} has no original in quarantine: only a failed MCAP import keeps one, "
            f"for {ledger.quarantine_days:g} days (FLEET_IMPORT_QUARANTINE_DAYS)"
        )
    return row.quarantine_key, ledger.warm.head(row.quarantine_key).size, safe_name(row.name)


def recover_interrupted(ledger: Ledger, staging: Path) -> int:
    """At start: imports this node was receiving or converting when it stopped are failed, saying
    so; an MCAP original that arrived whole waits in quarantine for a retry, and the file's digest
    is released. How many."""
    with session_scope(ledger.catalog) as session:
        found = [(r.id, r.kind, r.state, r.digest, r.name, r.bytes) for r in rows.interrupted(session, ledger.node_id)]
    for import_id, kind, state, digest, name, received in found:
        original = staging / import_id / "original.mcap"
        ledger.failed(
            import_id,
            received,
            f"interrupted: the depot stopped while it was {state} this upload"
            + ("; `fleet imports retry` converts it again" if kind == "mcap" and digest else "; send the file again"),
        )
        if digest is not None:
            with session_scope(ledger.catalog, write=True) as session:
                rows.release(session, digest, import_id)
            if original.exists():
                ledger.quarantine(import_id, original, name)
        shutil.rmtree(staging / import_id, ignore_errors=True)
    if found:
        log.info("%d imports interrupted by the last stop marked failed", len(found))
    return len(found)
