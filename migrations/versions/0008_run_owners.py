"""depot_nodes and run_owners: the depot's processes and which of them owns each hot run

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-25

Many depot processes share one catalog: each heart-beats in depot_nodes; the first to receive a
run's new chunks owns it in run_owners (until it seals the run, or stops heart-beating and another
takes it over, raising the epoch).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "depot_nodes",
        sa.Column("id", sa.String(length=256), nullable=False),
        sa.Column("peer_addr", sa.String(length=256), nullable=False),
        sa.Column("version", sa.String(length=64), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_depot_nodes")),
    )
    op.create_table(
        "run_owners",
        sa.Column("run_id", sa.String(length=128), nullable=False),
        sa.Column("node_id", sa.String(length=256), nullable=False),
        sa.Column("epoch", sa.BigInteger(), nullable=False),
        sa.Column("since", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("run_id", name=op.f("pk_run_owners")),
    )


def downgrade() -> None:
    op.drop_table("run_owners")
    op.drop_table("depot_nodes")
