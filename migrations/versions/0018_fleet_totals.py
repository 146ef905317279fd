"""fleet_totals: the whole-fleet sums the console's overview shows, as a job last counted them

Revision ID: 0018
Revises: 0017
Create Date: 2026-11-30

At a million runs the overview's sums (runs and bytes per robot and tier, objects and bytes per
store tier) took 2.2 s to count (BENCHMARKS.md) on every page view. Once a fleet is big a job counts
them every minute into this table and the overview reads them from here (`services.runs.totals`).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0018"
down_revision = "0017"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "fleet_totals",
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("computed_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("runs", sa.BigInteger(), nullable=False),
        sa.Column("body", sa.Text(), nullable=False),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_fleet_totals")),
    )


def downgrade() -> None:
    op.drop_table("fleet_totals")
