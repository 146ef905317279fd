"""The corpus as SQL tables: `run_metrics`, `events` and `run_tags`, with the columns people query
(an event's range as `start` and `end`; when a metric was computed or a tag added is left out).
Like the other catalog tables, their rows are read by the server and handed to the SQL worker as
Arrow tables: the worker never reaches the catalog."""

from __future__ import annotations

from typing import Any

from catalog.models import Event, RunMetric, RunTag

# table -> (column as SQL names it, the catalog's column), in order
CORPUS_TABLES: dict[str, tuple[tuple[str, Any], ...]] = {
    "run_metrics": (
        ("run_id", RunMetric.run_id),
        ("robot_id", RunMetric.robot_id),
        ("name", RunMetric.name),
        ("value", RunMetric.value),
        ("text_value", RunMetric.text_value),
        ("rules_version", RunMetric.rules_version),
    ),
    "events": (
        ("id", Event.id),
        ("run_id", Event.run_id),
        ("robot_id", Event.robot_id),
        ("kind", Event.kind),
        ("severity", Event.severity),
        ("timeline", Event.timeline),
        ("timeline_type", Event.timeline_type),
        ("start", Event.range_start),
        ("end", Event.range_end),
        ("source", Event.source),
        ("origin", Event.origin),
        ("rules_version", Event.rules_version),
        ("label", Event.label),
        ("note", Event.note),
        ("created_at", Event.created_at),
    ),
    "run_tags": (
        ("run_id", RunTag.run_id),
        ("tag", RunTag.tag),
        ("added_by", RunTag.added_by),
    ),
}
