"""Catalog reads and writes of imports (`imports`) and of the MCAP files held by digest
(`mcap_digests`): an import added as it starts, updated as it goes, listed newest first; an MCAP
file's digest claimed by one import (a primary key, so two uploads of one bag cannot both file it)
and released if that import fails.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import sqlalchemy as sa
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import session_scope
from catalog.models import Import, McapDigest

RECEIVING, CONVERTING, FILED, FAILED = "receiving", "converting", "filed", "failed"
STATES = (RECEIVING, CONVERTING, FILED, FAILED)
KINDS = ("rrd", "mcap")


def add(session: Session, row: Import) -> Import:
    session.add(row)
    session.flush()
    return row


def get(session: Session, import_id: str) -> Import | None:
    return session.get(Import, import_id, populate_existing=True)


def update(session: Session, import_id: str, now: dt.datetime, **values: Any) -> None:
    session.execute(sa.update(Import).where(Import.id == import_id).values(updated_at=now, **values))


def listed(
    session: Session, *, state: str | None, kind: str | None, robot: str | None, limit: int, before: str | None = None
) -> list[Import]:
    """Imports newest first, filtered; `before`: only those older than that import (paging)."""
    query = sa.select(Import).order_by(Import.created_at.desc(), Import.id.desc()).limit(limit)
    if state is not None:
        query = query.where(Import.state == state)
    if kind is not None:
        query = query.where(Import.kind == kind)
    if robot is not None:
        query = query.where(Import.robot_id == robot)
    if before is not None and (anchor := session.get(Import, before)) is not None:
        query = query.where(
            sa.or_(
                Import.created_at < anchor.created_at,
                sa.and_(Import.created_at == anchor.created_at, Import.id < anchor.id),
            )
        )
    return list(session.scalars(query))


def holder(session: Session, digest: str) -> McapDigest | None:
    """The import that holds (or is converting) the MCAP file of this digest."""
    return session.get(McapDigest, digest, populate_existing=True)


def claim(factory: sessionmaker[Session], digest: str, import_id: str, run_id: str) -> str | None:
    """Claim the MCAP file of `digest` for `import_id` in a transaction of its own; None if it was
    claimed, else the import that holds it (the primary key refused a second row)."""
    try:
        with session_scope(factory, write=True) as session:
            session.add(McapDigest(digest=digest, import_id=import_id, run_id=run_id))
            session.flush()
    except DBAPIError:
        with session_scope(factory) as session:
            found = holder(session, digest)
            if found is None:
                raise
            return found.import_id
    return None


def release(session: Session, digest: str, import_id: str) -> None:
    """Give up the claim of `import_id` on `digest` (its conversion failed: a later upload may try)."""
    session.execute(sa.delete(McapDigest).where(McapDigest.digest == digest, McapDigest.import_id == import_id))


def extension_candidates(session: Session, head_digest: str, data_end: int) -> list[Import]:
    """Filed MCAP imports that begin as this file does and whose data section is shorter than its:
    each may be an earlier copy of the same recording (the newcomer then extends it)."""
    query = (
        sa.select(Import)
        .where(
            Import.kind == "mcap",
            Import.state == FILED,
            Import.head_digest == head_digest,
            Import.held_by.is_(None),
            Import.data_end < data_end,
        )
        .order_by(Import.data_end.desc())
    )
    return list(session.scalars(query))


def longer_twins(session: Session, head_digest: str, data_end: int) -> list[Import]:
    """Filed MCAP imports that begin as this file does and hold a longer data section: this file
    may be an earlier copy of theirs."""
    query = sa.select(Import).where(
        Import.kind == "mcap",
        Import.state == FILED,
        Import.head_digest == head_digest,
        Import.held_by.is_(None),
        Import.data_end > data_end,
    )
    return list(session.scalars(query))


def quarantine_expired(session: Session, now: dt.datetime) -> list[Import]:
    """Failed imports whose original's time in quarantine is over."""
    query = sa.select(Import).where(Import.quarantine_key.is_not(None), Import.quarantine_until < now)
    return list(session.scalars(query))


def interrupted(session: Session, node: str) -> list[Import]:
    """Imports this node was receiving or converting when it stopped."""
    query = sa.select(Import).where(Import.node == node, Import.state.in_([RECEIVING, CONVERTING]))
    return list(session.scalars(query))
