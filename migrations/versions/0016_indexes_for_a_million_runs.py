"""indexes for a catalog of a million runs: the orders runs are listed in, and what retention reads

Revision ID: 0016
Revises: 0015
Create Date: 2026-11-30

At a million runs (`benchmarks/catalog_scale.py`, BENCHMARKS.md) these queries read every run:
`GET /v1/runs` newest first (its key is `coalesce(started_at, created_at)`, which no index held),
by robot, by size; sorted or filtered by a metric's value; the console's latest retention events and
jobs; retention's plan (sealed runs by tier and end, within an application its policy names; restores
under way). Postgres gets an index for each; `ix_run_metrics_name_value` and
`ix_runs_application_tier_end` replace the indexes of their first column. The embedded
catalog keeps primary keys only (see 0003). Building them on a million-run catalog takes about a
minute, during which the tables they index take no writes: upgrade with the depot stopped.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0016"
down_revision = "0015"
branch_labels = None
depends_on = None

RUN_START = sa.text("coalesce(started_at, created_at)")
RUN_END = sa.text("coalesce(ended_at, last_data_at)")
INDEXES: list[tuple[str, str, list[str | sa.TextClause]]] = [
    ("runs", "ix_runs_started", [RUN_START, "id"]),
    ("runs", "ix_runs_robot_started", ["robot_id", RUN_START, "id"]),
    ("runs", "ix_runs_bytes", ["bytes", "id"]),
    ("runs", "ix_runs_tier_end", ["tier", RUN_END]),
    ("runs", "ix_runs_application_tier_end", ["application_id", "tier", RUN_END]),
    ("run_metrics", "ix_run_metrics_name_value", ["name", "value", "run_id"]),
    ("retention_events", "ix_retention_events_occurred_at", ["occurred_at", "id"]),
    ("job_runs", "ix_job_runs_started_at", ["started_at", "id"]),
    ("run_lifecycle", "ix_run_lifecycle_restore_state", ["restore_state"]),
]
REPLACED = [("run_metrics", "ix_run_metrics_name", ["name"]), ("runs", "ix_runs_application_id", ["application_id"])]


def upgrade() -> None:
    if op.get_bind().dialect.name == "duckdb":
        return
    for table, name, columns in INDEXES:
        op.create_index(name, table, columns, unique=False)
    for table, name, _ in REPLACED:
        op.drop_index(name, table_name=table)


def downgrade() -> None:
    if op.get_bind().dialect.name == "duckdb":
        return
    for table, name, columns in REPLACED:
        op.create_index(name, table, list(columns), unique=False)
    for table, name, _ in reversed(INDEXES):
        op.drop_index(name, table_name=table)
