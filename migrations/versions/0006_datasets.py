"""datasets: the entry id (a TUID) of each application id, for Rerun's catalog protocol

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-23

Application ids already catalogued get theirs here; later ones when their first run is
catalogued (`catalog.queries.save_run`).
"""

from __future__ import annotations

import datetime as dt

import sqlalchemy as sa
from alembic import op

from core.ids import new_entry_id

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "datasets",
        sa.Column("name", sa.Text(), nullable=False),
        sa.Column("entry_id", sa.String(length=32), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_datasets")),
    )
    datasets = sa.table(
        "datasets",
        sa.column("name", sa.Text()),
        sa.column("entry_id", sa.String()),
        sa.column("created_at", sa.DateTime(timezone=True)),
        sa.column("updated_at", sa.DateTime(timezone=True)),
    )
    now = dt.datetime.now(dt.UTC)
    names = op.get_bind().execute(sa.text("SELECT DISTINCT application_id FROM runs WHERE application_id <> ''"))
    rows = [
        {"name": name, "entry_id": new_entry_id(name, int(now.timestamp() * 1e9)), "created_at": now, "updated_at": now}
        for (name,) in names
    ]
    if rows:
        op.bulk_insert(datasets, rows)


def downgrade() -> None:
    op.drop_table("datasets")
