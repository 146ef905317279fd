"""pulls and robot_copies: what the depot asks of robots' agents, and what they report holding

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24

A pull asks a robot's agent to send (part of) a run it holds; a robot copy is the agent's latest
report of what it holds of a run. Postgres indexes pulls by run and by robot (what the agents
poll); the embedded catalog keeps primary keys only (see 0003).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

INDEXES = [("ix_pulls_run_id", ["run_id"]), ("ix_pulls_robot_id", ["robot_id"])]


def upgrade() -> None:
    op.create_table(
        "pulls",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("run_id", sa.String(length=128), nullable=False),
        sa.Column("robot_id", sa.String(length=128), nullable=False),
        sa.Column("include", sa.Text(), nullable=False),
        sa.Column("exclude", sa.Text(), nullable=False),
        sa.Column("timeline", sa.Text(), nullable=True),
        sa.Column("start", sa.Text(), nullable=True),
        sa.Column("end", sa.Text(), nullable=True),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("requested_by", sa.String(length=256), nullable=False),
        sa.Column("requested_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("chunks_sent", sa.BigInteger(), nullable=False),
        sa.Column("bytes_sent", sa.BigInteger(), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_pulls")),
    )
    if op.get_bind().dialect.name != "duckdb":
        for name, columns in INDEXES:
            op.create_index(name, "pulls", columns, unique=False)
    op.create_table(
        "robot_copies",
        sa.Column("run_id", sa.String(length=128), nullable=False),
        sa.Column("robot_id", sa.String(length=128), nullable=False),
        sa.Column("reported_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("chunks", sa.BigInteger(), nullable=False),
        sa.Column("bytes", sa.BigInteger(), nullable=False),
        sa.Column("local_only_chunks", sa.BigInteger(), nullable=False),
        sa.Column("local_only_bytes", sa.BigInteger(), nullable=False),
        sa.Column("local_only_entities", sa.Text(), nullable=False),
        sa.Column("keeps_until", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("run_id", name=op.f("pk_robot_copies")),
    )


def downgrade() -> None:
    op.drop_table("robot_copies")
    if op.get_bind().dialect.name != "duckdb":
        for name, _ in INDEXES:
            op.drop_index(name, table_name="pulls")
    op.drop_table("pulls")
