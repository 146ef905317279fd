"""Catalog reads and writes of console sessions ended before their time (logged out)."""

from __future__ import annotations

import datetime as dt

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import EndedSession


def end_session(session: Session, session_id: str, token_id: str, expires_at: dt.datetime, now: dt.datetime) -> None:
    """Record that the session `session_id` ended (ending it again changes nothing), and forget the
    sessions whose cookies have expired by now: those are refused on their own."""
    session.execute(sa.delete(EndedSession).where(EndedSession.expires_at < now))
    if session.get(EndedSession, session_id) is None:
        session.add(EndedSession(id=session_id, token_id=token_id, ended_at=now, expires_at=expires_at))


def session_ended(session: Session, session_id: str) -> bool:
    return session.get(EndedSession, session_id) is not None
