"""Alembic migrations of the catalog (`fleet db upgrade`)."""
