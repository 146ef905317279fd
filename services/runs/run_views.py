"""What a run's page shows beyond `GET /v1/runs/{run}`: where each entity has data on a timeline
(from the run's chunk index, hot or sealed alike) and what retention will do to the run next."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from core.clock import aware, utcnow
from core.errors import ConflictError, GoneError, NotFoundError
from core.states import RestoreState, Tier
from services.hot.read import HotRuns
from services.policies import Policies
from services.rrd.chunk_index import CHUNK, IndexRow
from services.sealed.read import locate_sealed
from services.storage.objectstore import ObjectStore


@dataclass(frozen=True)
class Coverage:
    """Where each entity has data on one timeline, and the whole span of that timeline."""

    timeline: str
    type: str  # sequence | timestamp | duration
    lo: int
    hi: int
    rows: list[tuple[str, int, int]]  # entity, first, last


@dataclass(frozen=True)
class NextStep:
    """What retention will do to a run next, when and why (None `at`: not planned)."""

    action: str  # promote | archive | delete | restore-ends | nothing
    at: str | None
    reason: str


def index_rows(
    hot_runs: HotRuns | None, catalog: sessionmaker[Session], warm: ObjectStore, run_id: str
) -> list[IndexRow]:
    """The run's chunk index: the hot file's here, else the sealed run's (NotFound, Conflict for a
    cold run not restored, Gone for a deleted one: the caller shows why there is none)."""
    hot = hot_runs.hot_recording(run_id) if hot_runs is not None else None
    if hot is not None:
        return hot.chunk_index().rows
    return locate_sealed(catalog, warm, run_id, utcnow()).rows


def coverage(rows: list[IndexRow], timeline: str | None = None, most: int = 64) -> Coverage | None:
    """Per entity, the first and last time on `timeline` (default: the first sequence timeline,
    else the first one) over its non-static chunks; at most `most` entities, by path."""
    chunks = [r for r in rows if r.kind == CHUNK and r.store_kind == "recording" and not r.is_static and r.entity_path]
    types: dict[str, str] = {}
    for row in chunks:
        for t in row.timelines:
            types.setdefault(t.name, t.type)
    if not types:
        return None
    if timeline not in types:
        sequences = sorted(name for name, kind in types.items() if kind == "sequence")
        timeline = sequences[0] if sequences else sorted(types)[0]
    spans: dict[str, tuple[int, int]] = {}
    for row in chunks:
        for t in row.timelines:
            if t.name == timeline and row.entity_path is not None:
                lo, hi = spans.get(row.entity_path, (t.min, t.max))
                spans[row.entity_path] = (min(lo, t.min), max(hi, t.max))
    if not spans:
        return None
    ordered = sorted(spans.items())[:most]
    return Coverage(
        timeline,
        types[timeline],
        min(lo for lo, _ in spans.values()),
        max(hi for _, hi in spans.values()),
        [(path, lo, hi) for path, (lo, hi) in ordered],
    )


def run_coverage(
    hot_runs: HotRuns | None,
    catalog: sessionmaker[Session],
    warm: ObjectStore,
    run_id: str,
    timeline: str | None = None,
) -> tuple[Coverage | None, str | None]:
    """The run's coverage, or None and why it cannot be read now (a cold run, a deleted one)."""
    try:
        return coverage(index_rows(hot_runs, catalog, warm, run_id), timeline), None
    except (ConflictError, GoneError, NotFoundError) as exc:
        return None, exc.message


def next_step(answer: dict[str, Any], policies: Policies | None, now: dt.datetime | None = None) -> NextStep:
    """What retention does next to the run `answer` (`run_answer`) describes, by its policy."""
    tier = answer["tier"]
    if tier == Tier.DELETED:
        return NextStep("nothing", None, "the run is deleted; its tombstone stays")
    if tier == Tier.HOT:
        return NextStep("promote", None, "sealed into the warm tier once closed and idle (FLEET_PROMOTE_AFTER_S)")
    if policies is None:
        return NextStep("nothing", None, "this node runs no retention")
    now = now or utcnow()
    policy = policies.for_run(answer["robot_id"], answer["application_id"])
    ended_text = answer.get("ended_at") or answer.get("last_data_at")
    if not ended_text:
        return NextStep("nothing", None, "the run has no end time yet")
    ended = aware(dt.datetime.fromisoformat(str(ended_text).replace("Z", "+00:00")))
    life = answer.get("lifecycle") or {}
    if life.get("restore_state") == RestoreState.RESTORING:
        return NextStep("restore", None, "a restore was asked for: the retention job finishes it")
    if life.get("restore_state") == RestoreState.RESTORED and life.get("restore_until"):
        return NextStep("restore-ends", life["restore_until"], "the restored copy is readable until then")
    delete_at = ended + policy.delete_after
    if answer.get("pinned"):
        keep = f"pinned by {answer.get('pinned_by') or 'someone'}: never deleted while pinned"
        if tier == Tier.WARM and policy.cold_days > 0:
            return NextStep("archive", _iso(ended + policy.archive_after, now), f"policy {policy.name!r}; {keep}")
        return NextStep("nothing", None, keep)
    if tier == Tier.WARM and policy.cold_days > 0:
        return NextStep(
            "archive",
            _iso(ended + policy.archive_after, now),
            f"policy {policy.name!r} keeps runs {policy.warm_days:g} days warm, then {policy.cold_days:g} days cold",
        )
    return NextStep(
        "delete",
        _iso(delete_at, now),
        f"policy {policy.name!r} keeps runs {policy.warm_days:g} days warm + {policy.cold_days:g} days cold",
    )


def _iso(when: dt.datetime, now: dt.datetime) -> str:
    """When a step is due: the next retention run if it is overdue already."""
    return max(when, now).isoformat()
