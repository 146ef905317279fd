"""The overview's whole-fleet sums: runs per robot, runs and bytes per tier, objects and bytes per
store tier.

Counting them reads every run and every sealed object: 2.2 s at a million runs (BENCHMARKS.md), too
long for each view of the console's first page. So a job counts them every minute (`count_job`) into
the catalog (`fleet_totals`), and the overview of a big fleet (BIG_FLEET runs or more at the last
count) shows that count and when it was made. A smaller fleet is counted as the overview is asked,
as is any fleet whose last count is older than STALE_AFTER (the job stopped, or never ran)."""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import asdict, dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import insert
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import session_scope
from catalog.models import FleetTotals, Run, RunObject
from core.clock import aware, iso_utc
from core.states import Tier

BIG_FLEET = 50_000  # runs: from here on the overview shows the job's count
COUNT_INTERVAL_S = 60.0  # how often the job counts
STALE_AFTER = dt.timedelta(seconds=5 * COUNT_INTERVAL_S)  # a count older than this is not shown
OVERVIEW = "overview"  # the row of fleet_totals the job writes
TIERS = (Tier.HOT, Tier.WARM, Tier.COLD)


@dataclass
class Totals:
    robots: dict[str, int]  # robot id -> runs (deleted runs not counted)
    tiers: list[dict[str, Any]]  # per tier: runs and their recordings' bytes; deleted runs as tombstones
    objects: list[dict[str, Any]]  # per store tier (warm, cold): objects and bytes
    runs: int  # every run row, tombstones included
    counted_at: str | None = None  # when the job counted them (ISO); None: counted for this answer


def count(session: Session) -> Totals:
    """The sums, counted now."""
    per_tier: dict[str, tuple[int, int]] = {}
    robots: dict[str, int] = {}
    query = sa.select(Run.robot_id, Run.tier, sa.func.count(), sa.func.sum(Run.bytes)).group_by(Run.robot_id, Run.tier)
    for robot_id, tier, n, size in session.execute(query).all():
        runs, held = per_tier.get(tier, (0, 0))
        per_tier[tier] = (runs + int(n), held + int(size or 0))
        if tier != Tier.DELETED:
            robots[robot_id] = robots.get(robot_id, 0) + int(n)
    tiers = [{"tier": str(t), "runs": per_tier.get(t, (0, 0))[0], "bytes": per_tier.get(t, (0, 0))[1]} for t in TIERS]
    tiers.append({"tier": str(Tier.DELETED), "runs": per_tier.get(Tier.DELETED, (0, 0))[0], "bytes": None})
    stored = {
        tier: (int(n), int(size or 0))
        for tier, n, size in session.execute(
            sa.select(RunObject.tier, sa.func.count(), sa.func.sum(RunObject.size)).group_by(RunObject.tier)
        ).all()
    }
    objects = [
        {"tier": str(t), "objects": stored.get(t, (0, 0))[0], "bytes": stored.get(t, (0, 0))[1]}
        for t in (Tier.WARM, Tier.COLD)
    ]
    return Totals(robots, tiers, objects, sum(runs for runs, _ in per_tier.values()))


def totals(session: Session, now: dt.datetime) -> Totals:
    """The sums the overview shows: the job's last count for a big fleet, else counted now."""
    row = session.get(FleetTotals, OVERVIEW)
    if row is None or row.runs < BIG_FLEET or now - aware(row.computed_at) > STALE_AFTER:
        return count(session)
    return Totals(**{**json.loads(row.body), "counted_at": iso_utc(row.computed_at)})


def count_job(catalog: sessionmaker[Session], now: dt.datetime) -> int | None:
    """Count the sums and keep them for the overview (a re-runnable job: the last count wins);
    the runs counted, or None where another node counted them less than an interval ago."""
    with session_scope(catalog) as session:
        row = session.get(FleetTotals, OVERVIEW)
        if row is not None and now - aware(row.computed_at) < dt.timedelta(seconds=0.9 * COUNT_INTERVAL_S):
            return None
        counted = count(session)
    values = {"name": OVERVIEW, "computed_at": now, "runs": counted.runs, "body": json.dumps(asdict(counted))}
    statement = insert(FleetTotals).values(values)
    with session_scope(catalog, write=True) as session:  # two nodes' jobs at once: the last count wins
        session.execute(statement.on_conflict_do_update(index_elements=["name"], set_=values))
    return counted.runs
