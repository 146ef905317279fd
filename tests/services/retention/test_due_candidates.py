"""The retention plan reads only the sealed runs it may act on (`may_be_due`: by tier and end, each
policy's runs as `Policies.for_run` names them), and plans exactly what it planned reading them all."""

from __future__ import annotations

import datetime as dt
import itertools
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.models import RunLifecycle
from core.states import RestoreState, Tier
from services.policies import Policies, Policy, PolicyOverride
from services.retention import service
from services.retention.service import ACTIONS, Retention
from tests.catalog.records import run_record
from tests.services.nodes import node_of

NOW = dt.datetime(2026, 12, 5, 12, 0, tzinfo=dt.UTC)
POLICIES = Policies(
    Policy("default", 30, 365),
    (
        PolicyOverride.model_validate({"name": "bench", "robot": "bench-1", "warm_days": 2, "cold_days": 5}),
        # a second override of the same robot: the first wins
        PolicyOverride.model_validate({"name": "again", "robot": "bench-1", "warm_days": 100, "cold_days": 100}),
        PolicyOverride.model_validate({"name": "mapping", "application": "mapping", "warm_days": 7, "cold_days": 60}),
        PolicyOverride.model_validate({"name": "no-cold", "application": "scratch", "warm_days": 3, "cold_days": 0}),
    ),
)
ROBOTS = ("bench-1", "robot-1")
APPLICATIONS = ("mapping", "scratch", "nav")
# Ages around every policy's boundaries: just under and just over each.
AGES = sorted({d + s for d in (2, 3, 7, 30, 67, 395) for s in (-0.001, 0.001)})


def _sealed(session: Session, run_id: str, robot: str, application: str, tier: str, age_days: float) -> None:
    end = NOW - dt.timedelta(days=age_days)
    record = run_record(run_id, end, robot_id=robot, application_id=application, tier=tier, started_at=end)
    queries.save_run(session, record, end)
    restore = RestoreState.RESTORED if run_id.endswith("7") and tier == Tier.COLD else None
    until = NOW - dt.timedelta(days=1) if restore else None  # its restore period over: to archive again
    life = RunLifecycle(run_id=run_id, prefix=f"{robot}/{run_id}", promoted_at=end, restore_state=restore)
    life.restore_until = until
    session.add(life)


@pytest.fixture
def fleet(catalog: sessionmaker[Session]) -> sessionmaker[Session]:
    """Warm and cold runs of each robot and application at each age, some pinned, one restored."""
    with session_scope(catalog, write=True) as session:
        combos = itertools.product(ROBOTS, APPLICATIONS, (Tier.WARM, Tier.COLD), AGES)
        for n, (robot, application, tier, age) in enumerate(combos):
            _sealed(session, f"run-{n}", robot, application, tier, age)
        session.flush()
        for run in queries.get_runs(session, [f"run-{n}" for n in range(0, 200, 9)]).values():
            run.pinned, run.pinned_by = True, "alice"
    return catalog


def _reference(session: Session) -> set[str]:
    """The runs past their policy's archive age (warm, archiving) or deletion age, or restored."""
    found = set()
    for run, life in queries.sealed_runs(session, (Tier.WARM, Tier.COLD)):
        policy = POLICIES.for_run(run.robot_id, run.application_id)
        age = NOW - queries.run_record(session, run.id).ended_at  # type: ignore[operator,union-attr]
        archiving = run.tier == Tier.WARM and policy.cold_days > 0 and age >= policy.archive_after
        if age >= policy.delete_after or archiving or life.restore_state is not None:
            found.add(run.id)
    return found


def test_the_catalog_reads_exactly_the_runs_past_an_age_or_restored(fleet: sessionmaker[Session]):
    with session_scope(fleet) as session:
        due = queries.sealed_runs(session, (Tier.WARM, Tier.COLD), service.may_be_due(POLICIES, NOW))
        found, expected = {run.id for run, _ in due}, _reference(session)
    assert found == expected
    assert 0 < len(expected) < len(ROBOTS) * len(APPLICATIONS) * 2 * len(AGES)


def test_the_plan_is_the_one_reading_every_sealed_run_gives(
    fleet: sessionmaker[Session], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    ctx = Retention(node=node_of(tmp_path, fleet, clock=lambda: NOW), policies=POLICIES)
    read_some = service.plan_answer(ctx, list(ACTIONS))
    monkeypatch.setattr(service, "may_be_due", lambda policies, now: sa.true())
    read_all = service.plan_answer(ctx, list(ACTIONS))
    assert read_some == read_all
    assert {a["action"] for a in read_all["actions"]} == {"archive", "delete", "restore"}
    assert read_all["kept"]  # pinned runs past their deletion, each with why
