"""ended_sessions: console sessions ended by logging out, refused from then on

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-28

A console session is a signed cookie that names its token; logging out records the session's id
here so the cookie, still signed and unexpired, is refused on every node. A row is kept only until
the cookie would have expired anyway (at most 12 hours).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "ended_sessions",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("token_id", sa.String(length=32), nullable=False),
        sa.Column("ended_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_ended_sessions")),
    )


def downgrade() -> None:
    op.drop_table("ended_sessions")
