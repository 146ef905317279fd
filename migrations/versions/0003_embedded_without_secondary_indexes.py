"""embedded catalog: no secondary indexes

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-21

DuckDB 1.5 rewrites a row's index entries when an indexed column is updated, and after a process
is killed its persisted secondary indexes can disagree with the rows: the next update of such a
row fails with a FATAL "Failed to delete all rows from index" that invalidates the database. The
embedded catalog is small enough to scan, so it keeps only primary keys; Postgres keeps its indexes.
"""

from __future__ import annotations

from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

INDEXES = [
    ("runs", "ix_runs_application_id", ["application_id"]),
    ("runs", "ix_runs_date", ["date"]),
    ("runs", "ix_runs_robot_id", ["robot_id"]),
    ("runs", "ix_runs_started_at", ["started_at"]),
    ("runs", "ix_runs_status", ["status"]),
    ("runs", "ix_runs_tier", ["tier"]),
    ("job_runs", "ix_job_runs_job", ["job"]),
    ("retention_events", "ix_retention_events_run_id", ["run_id"]),
]


def upgrade() -> None:
    if op.get_bind().dialect.name != "duckdb":
        return
    for table, name, _ in INDEXES:
        op.drop_index(name, table_name=table)


def downgrade() -> None:
    if op.get_bind().dialect.name != "duckdb":
        return
    for table, name, columns in INDEXES:
        op.create_index(name, table, columns, unique=False)
