"""Alembic environment: runs on the connection `catalog.db.upgrade` hands over."""

from __future__ import annotations

from alembic import context

import catalog.db  # noqa: F401  (registers DuckDB with Alembic)
from catalog.models import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=False)
with context.begin_transaction():
    context.run_migrations()
