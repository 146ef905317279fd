"""dataset_columns: what each dataset's runs have held that its segment table makes columns of

Revision ID: 0017
Revises: 0016
Create Date: 2026-11-30

The segment table's schema (a column per recording property, property archetype, timeline and
metric any run of the dataset has) was found by reading every run of the dataset before the first
row went out: 16-24 s at a million runs (BENCHMARKS.md). Writers now count these as they write a run
(`catalog.dataset_columns`); the upgrade counts what the runs already hold, reading every run once
(about a minute at a million runs).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.orm import Session

from catalog.dataset_columns import refill

revision = "0017"
down_revision = "0016"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "dataset_columns",
        sa.Column("application_id", sa.Text(), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("name", sa.Text(), nullable=False),
        sa.Column("detail", sa.Text(), nullable=False),
        sa.Column("runs", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("application_id", "kind", "name", "detail", name=op.f("pk_dataset_columns")),
    )
    refill(Session(bind=op.get_bind()))


def downgrade() -> None:
    op.drop_table("dataset_columns")
