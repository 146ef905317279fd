"""lakehouse_runs: which change of each run's analytics files the Iceberg tables hold

Revision ID: 0019
Revises: 0018
Create Date: 2026-11-30

The lakehouse (`services.lakehouse`) copies each run's analytics rows and catalog rows (run, metrics,
events, tags) into Iceberg tables that outside engines read. Writers that change them (sealing,
extraction, the rules, people's tags and events, archive, deletion) mark the run pending in their own
transaction; the sync job copies pending runs and clears the mark.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0019"
down_revision = "0018"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "lakehouse_runs",
        sa.Column("run_id", sa.String(length=128), nullable=False),
        sa.Column("wanted", sa.BigInteger(), nullable=False),
        sa.Column("synced", sa.BigInteger(), nullable=False),
        sa.Column("pending", sa.Boolean(), nullable=False),
        sa.Column("telemetry", sa.Boolean(), nullable=False),
        sa.Column("synced_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("rows", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("run_id", name=op.f("pk_lakehouse_runs")),
    )
    if op.get_bind().dialect.name != "duckdb":  # the embedded catalog keeps primary keys only (0003)
        op.create_index("ix_lakehouse_runs_pending", "lakehouse_runs", ["run_id"], postgresql_where=sa.text("pending"))


def downgrade() -> None:
    if op.get_bind().dialect.name != "duckdb":
        op.drop_index("ix_lakehouse_runs_pending", table_name="lakehouse_runs")
    op.drop_table("lakehouse_runs")
