"""What the corpus knows of one run, as `GET /v1/runs/RUN` shows it: its metrics (and the rules
version that computed them), its tags (who added each, when), its events counted by kind, and how
its evaluation went."""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from catalog import corpus
from core.clock import iso_utc


def corpus_answer(session: Session, run_id: str) -> dict[str, Any]:
    """`metrics` {name: number or text}, `metrics_rules_version` (None without metrics), `tags`
    [{tag, added_by, added_at}], `event_counts` {kind: count} and `evaluation` (None before any)."""
    metrics = corpus.metrics_of(session, run_id)
    evaluation = corpus.evaluation_of(session, run_id)
    return {
        "metrics": {m.name: m.text_value if m.text_value is not None else m.value for m in metrics},
        "metrics_rules_version": max((m.rules_version for m in metrics), default=None),
        "tags": [
            {"tag": t.tag, "added_by": t.added_by, "added_at": iso_utc(t.added_at)}
            for t in corpus.tags_of(session, run_id)
        ],
        "event_counts": corpus.event_counts_of(session, run_id),
        "evaluation": None
        if evaluation is None
        else {
            "rules_version": evaluation.rules_version,
            "state": evaluation.state,
            "events_capped": evaluation.events_capped,
            "note": evaluation.note,
            "evaluated_at": iso_utc(evaluation.evaluated_at),
        },
    }
