"""Catalog reads and writes of tokens: what each grants, and whether it was revoked."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import ApiToken
from core.clock import aware
from core.errors import NotFoundError


@dataclass(frozen=True)
class TokenRecord:
    id: str
    name: str
    subject: str
    scopes: tuple[str, ...]
    robot_id: str | None
    created_at: dt.datetime
    created_by: str
    expires_at: dt.datetime | None
    revoked_at: dt.datetime | None = None
    revoked_by: str | None = None


def add_token(session: Session, record: TokenRecord) -> None:
    session.add(
        ApiToken(
            id=record.id,
            name=record.name,
            subject=record.subject,
            scopes=" ".join(record.scopes),
            robot_id=record.robot_id,
            created_at=record.created_at,
            created_by=record.created_by,
            expires_at=record.expires_at,
            revoked_at=None,
            revoked_by=None,
        )
    )


def token_record(session: Session, token_id: str) -> TokenRecord | None:
    row = session.get(ApiToken, token_id)
    return _record(row) if row is not None else None


def token_records(session: Session, *, include_revoked: bool = False) -> list[TokenRecord]:
    query = sa.select(ApiToken).order_by(ApiToken.created_at, ApiToken.id)
    if not include_revoked:
        query = query.where(ApiToken.revoked_at.is_(None))
    return [_record(row) for row in session.scalars(query)]


def revoke_token(session: Session, token_id: str, now: dt.datetime, actor: str) -> TokenRecord:
    """Mark a token revoked (revoking it again changes nothing)."""
    row = session.get(ApiToken, token_id)
    if row is None:
        raise NotFoundError(f"no token {token_id!r}: `fleet tokens ls` lists them")
    if row.revoked_at is None:
        row.revoked_at, row.revoked_by = now, actor
    return _record(row)


def _record(row: ApiToken) -> TokenRecord:
    return TokenRecord(
        id=row.id,
        name=row.name,
        subject=row.subject,
        scopes=tuple(row.scopes.split()),
        robot_id=row.robot_id,
        created_at=aware(row.created_at),
        created_by=row.created_by,
        expires_at=aware(row.expires_at) if row.expires_at is not None else None,
        revoked_at=aware(row.revoked_at) if row.revoked_at is not None else None,
        revoked_by=row.revoked_by,
    )
