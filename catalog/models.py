"""Catalog tables: robots, runs, and per-run entities and timelines.

The same models serve Postgres (production) and DuckDB (embedded default); types are chosen to
mean the same on both (JSON kept as text, timestamps with time zone, 64-bit integers). There are
no foreign keys: DuckDB refuses to update a row that another table references within the same
transaction, and the catalog writes a run with its entities and timelines together
(`catalog.queries.save_run`), which keeps them consistent.
"""

from __future__ import annotations

import datetime as dt

from sqlalchemy import BigInteger, Boolean, Date, DateTime, MetaData, String, Text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

ID_LENGTH = 128  # ids used in object keys: [A-Za-z0-9._-]{1,128}

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


class Robot(Base):
    __tablename__ = "robots"

    id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    last_seen_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class Run(Base):
    """One recording (run id = Rerun recording id), filed under robot/date/run."""

    __tablename__ = "runs"

    id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH), index=True)
    application_id: Mapped[str] = mapped_column(String(256), index=True)
    date: Mapped[dt.date] = mapped_column(Date, index=True)  # UTC date of the run's start
    status: Mapped[str] = mapped_column(String(16), index=True)  # live | closed
    tier: Mapped[str] = mapped_column(String(16), index=True)  # hot | warm | cold | deleted
    started_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True), index=True)
    ended_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    last_data_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    sdk_version: Mapped[str | None] = mapped_column(String(64))
    chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    rows: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    properties: Mapped[str] = mapped_column(Text, default="{}")  # JSON object, secrets removed
    pinned: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class RunEntity(Base):
    __tablename__ = "run_entities"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    path: Mapped[str] = mapped_column(Text, primary_key=True)
    chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    static_chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    rows: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    archetypes: Mapped[str] = mapped_column(Text, default="[]")  # JSON list
    components: Mapped[str] = mapped_column(Text, default="[]")  # JSON list


class RunTimeline(Base):
    __tablename__ = "run_timelines"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    name: Mapped[str] = mapped_column(String(256), primary_key=True)
    type: Mapped[str] = mapped_column(String(16))  # sequence | timestamp | duration
    min: Mapped[int] = mapped_column(BigInteger)
    max: Mapped[int] = mapped_column(BigInteger)
