"""names as long as the SDK makes them; who pinned a run kept on the run

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-22

Application ids and timeline names were VARCHAR(256) on Postgres: a longer one (ordinary SDK use)
failed every later catalog write of the node. They are TEXT now (ingest bounds them by bytes, so
Postgres indexes can hold them). A pin lived on the run and its owner on the lifecycle row, which
only exists once a run is sealed, so a pin set while a run was hot lost its owner: both now live on
the run. DuckDB's VARCHAR has no length, so only the pin moves there.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    postgres = op.get_bind().dialect.name == "postgresql"
    if postgres:
        op.alter_column(
            "runs", "application_id", type_=sa.Text(), existing_type=sa.String(length=256), existing_nullable=False
        )
        op.alter_column(
            "run_timelines", "name", type_=sa.Text(), existing_type=sa.String(length=256), existing_nullable=False
        )
    op.add_column("runs", sa.Column("pinned_by", sa.String(length=256), nullable=True))
    op.execute(
        "UPDATE runs SET pinned_by = (SELECT l.pinned_by FROM run_lifecycle l WHERE l.run_id = runs.id) WHERE pinned"
    )
    op.drop_column("run_lifecycle", "pinned_by")


def downgrade() -> None:
    op.add_column("run_lifecycle", sa.Column("pinned_by", sa.String(length=256), nullable=True))
    op.execute(
        "UPDATE run_lifecycle SET pinned_by = (SELECT r.pinned_by FROM runs r WHERE r.id = run_lifecycle.run_id)"
    )
    op.drop_column("runs", "pinned_by")
    if op.get_bind().dialect.name == "postgresql":
        op.alter_column(
            "run_timelines", "name", type_=sa.String(length=256), existing_type=sa.Text(), existing_nullable=False
        )
        op.alter_column(
            "runs", "application_id", type_=sa.String(length=256), existing_type=sa.Text(), existing_nullable=False
        )
