"""saved_queries: SQL queries saved from the console, drawn on its dashboards

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-26

Each row is a query with a unique name and the chart it is drawn as (line, bar or table); its
result is computed at every look, never stored. Postgres holds the names unique with an index; the
embedded catalog keeps primary keys only (see 0003) and the catalog code checks names itself.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "saved_queries",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("name", sa.String(length=256), nullable=False),
        sa.Column("sql", sa.Text(), nullable=False),
        sa.Column("chart", sa.String(length=16), nullable=False),
        sa.Column("created_by", sa.String(length=256), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_saved_queries")),
    )
    if op.get_bind().dialect.name != "duckdb":
        op.create_index("ix_saved_queries_name", "saved_queries", ["name"], unique=True)


def downgrade() -> None:
    if op.get_bind().dialect.name != "duckdb":
        op.drop_index("ix_saved_queries_name", table_name="saved_queries")
    op.drop_table("saved_queries")
