"""dataset exports: jobs that write a snapshot version as a LeRobot dataset, with their progress

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-02

`fleet datasets export NAME@N --to s3://...` (`POST /v1/exports`) queues a job; a depot process
claims it (`node`, `heartbeat_at`), writes the episodes with progress, and another takes it over if
its heartbeat stops (the export resumes after its last written episode). `report` holds the quality
flags of each flagged or skipped episode (JSON).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None


def _count(name: str) -> sa.Column:  # type: ignore[type-arg]
    return sa.Column(name, sa.BigInteger(), nullable=False)


def upgrade() -> None:
    op.create_table(
        "dataset_exports",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("version", sa.BigInteger(), nullable=False),
        sa.Column("format", sa.String(length=16), nullable=False),
        sa.Column("spec", sa.Text(), nullable=False),
        sa.Column("target", sa.Text(), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        _count("episodes"),
        _count("done"),
        _count("frames"),
        _count("skipped"),
        _count("flagged"),
        _count("bytes"),
        sa.Column("report", sa.Text(), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("created_by", sa.String(length=256), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("node", sa.String(length=256), nullable=True),
        sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_dataset_exports")),
    )


def downgrade() -> None:
    op.drop_table("dataset_exports")
