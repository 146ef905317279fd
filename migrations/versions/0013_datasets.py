"""dataset snapshots: named snapshots, their immutable versions, and each version's episodes

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-01

A dataset snapshot (`fleet datasets create NAME`) is a selection of runs resolved into a version
`NAME@N` listing its episodes: a run, whole or a window around one of its events, and the chunk ids
it reads. The tables are `dataset_snapshots`, `dataset_versions`, `dataset_episodes` (`datasets`
holds Rerun's catalog protocol datasets since 0006). Postgres indexes episodes by run (what
retention asks: which snapshots use these runs); the embedded catalog keeps primary keys only (see
0003).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None

INDEX = ("ix_dataset_episodes_run_id", ["run_id"])


def _text(name: str, length: int, nullable: bool = False) -> sa.Column:  # type: ignore[type-arg]
    return sa.Column(name, sa.String(length=length), nullable=nullable)


def _count(name: str, nullable: bool = False) -> sa.Column:  # type: ignore[type-arg]
    return sa.Column(name, sa.BigInteger(), nullable=nullable)


def upgrade() -> None:
    op.create_table(
        "dataset_snapshots",
        _text("name", 64),
        _text("created_by", 256),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_dataset_snapshots")),
    )
    op.create_table(
        "dataset_versions",
        _text("name", 64),
        sa.Column("version", sa.BigInteger(), autoincrement=False, nullable=False),
        sa.Column("selection", sa.Text(), nullable=False),
        _text("created_by", 256),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        _count("rules_version", nullable=True),
        _count("episodes"),
        _count("runs"),
        _count("chunks"),
        _count("bytes"),
        sa.Column("skipped", sa.Text(), nullable=False),
        sa.PrimaryKeyConstraint("name", "version", name=op.f("pk_dataset_versions")),
    )
    op.create_table(
        "dataset_episodes",
        _text("name", 64),
        sa.Column("version", sa.BigInteger(), autoincrement=False, nullable=False),
        sa.Column("episode", sa.BigInteger(), autoincrement=False, nullable=False),
        _text("run_id", 128),
        _text("robot_id", 128),
        _text("split", 32, nullable=True),
        _text("timeline", 256),
        _count("range_start", nullable=True),
        _count("range_end", nullable=True),
        _text("event_id", 32, nullable=True),
        sa.Column("chunk_ids", sa.LargeBinary(), nullable=False),
        _count("chunks"),
        _count("bytes"),
        sa.PrimaryKeyConstraint("name", "version", "episode", name=op.f("pk_dataset_episodes")),
    )
    if op.get_bind().dialect.name != "duckdb":
        name, columns = INDEX
        op.create_index(name, "dataset_episodes", columns, unique=False)


def downgrade() -> None:
    if op.get_bind().dialect.name != "duckdb":
        op.drop_index(INDEX[0], table_name="dataset_episodes")
    for table in ("dataset_episodes", "dataset_versions", "dataset_snapshots"):
        op.drop_table(table)
