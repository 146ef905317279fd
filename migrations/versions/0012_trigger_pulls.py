"""trigger pulls: where a pull comes from, the event whose window it brings, its priority

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-30

A pull is a person's (`origin` person: every pull before this revision) or a trigger's (`origin`
trigger: queued by the depot's live rules for a new event, or reported by the robot's agent that
fired it), with the event it brings the window of (`event_id`, also set on a person's pull made
from an event) and a trigger's priority. Postgres indexes pulls by event (what an event's answer
reads); the embedded catalog keeps primary keys only (see 0003). DuckDB adds no column with a
constraint: there the column comes nullable with its default, and is made not null after.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None

INDEX = ("ix_pulls_event_id", ["event_id"])


def upgrade() -> None:
    duckdb = op.get_bind().dialect.name == "duckdb"
    op.add_column("pulls", sa.Column("origin", sa.String(length=16), nullable=duckdb, server_default="person"))
    if duckdb:
        op.execute("UPDATE pulls SET origin = 'person' WHERE origin IS NULL")
        op.execute("ALTER TABLE pulls ALTER COLUMN origin SET NOT NULL")
    op.add_column("pulls", sa.Column("event_id", sa.String(length=32), nullable=True))
    op.add_column("pulls", sa.Column("priority", sa.String(length=8), nullable=True))
    if not duckdb:
        name, columns = INDEX
        op.create_index(name, "pulls", columns, unique=False)


def downgrade() -> None:
    if op.get_bind().dialect.name != "duckdb":
        op.drop_index(INDEX[0], table_name="pulls")
    for column in ("priority", "event_id", "origin"):
        op.drop_column("pulls", column)
