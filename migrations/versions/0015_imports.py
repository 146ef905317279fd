"""imports: every upload (RRD or MCAP) with its state, and the MCAP files held by content digest

Revision ID: 0015
Revises: 0014
Create Date: 2026-12-03

`GET /v1/imports` lists uploads as they are received, converted (MCAP), filed or failed with why.
An MCAP file's identity is its content digest (`mcap_digests`, one row per file: conversion makes
fresh chunk ids each time); a failed MCAP's original waits in the quarantine prefix for a retry.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "imports",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("kind", sa.String(length=8), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("name", sa.String(length=256), nullable=False),
        sa.Column("bytes", sa.BigInteger(), nullable=False),
        sa.Column("robot_id", sa.String(length=128), nullable=True),
        sa.Column("run_ids", sa.Text(), nullable=False),
        sa.Column("application_id", sa.String(length=256), nullable=True),
        sa.Column("chunks_new", sa.BigInteger(), nullable=False),
        sa.Column("chunks_duplicate", sa.BigInteger(), nullable=False),
        sa.Column("reason", sa.Text(), nullable=True),
        sa.Column("digest", sa.String(length=64), nullable=True),
        sa.Column("head_digest", sa.String(length=64), nullable=True),
        sa.Column("data_end", sa.BigInteger(), nullable=True),
        sa.Column("data_digest", sa.String(length=64), nullable=True),
        sa.Column("held_by", sa.String(length=32), nullable=True),
        sa.Column("converter", sa.String(length=64), nullable=True),
        sa.Column("quarantine_key", sa.Text(), nullable=True),
        sa.Column("quarantine_until", sa.DateTime(timezone=True), nullable=True),
        sa.Column("node", sa.String(length=256), nullable=True),
        sa.Column("created_by", sa.String(length=256), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_imports")),
    )
    op.create_table(
        "mcap_digests",
        sa.Column("digest", sa.String(length=64), nullable=False),
        sa.Column("import_id", sa.String(length=32), nullable=False),
        sa.Column("run_id", sa.String(length=128), nullable=False),
        sa.PrimaryKeyConstraint("digest", name=op.f("pk_mcap_digests")),
    )


def downgrade() -> None:
    op.drop_table("mcap_digests")
    op.drop_table("imports")
