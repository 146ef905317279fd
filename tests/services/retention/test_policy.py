"""Retention policies: a default plus overrides by robot (first choice) or application, read from
the settings (a JSON list in FLEET_RETENTION_POLICIES or TOML [[retention_policies]] tables),
shown at GET /v1/retention, and applied per run (a bench robot's 7 days against production's 365)."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from catalog.db import create_engine, upgrade
from services.api.app import create_app
from services.policies import Policies, Policy, PolicyOverride
from services.retention.schedule import retention_job
from services.retention.service import plan, run_plan
from services.sealed.tiers import Tiers
from services.server import build
from services.settings import load_settings
from tests.services.retention.conftest import Clock, Node, NodeFactory, listing, log_run


def override(**fields: Any) -> PolicyOverride:
    return PolicyOverride.model_validate(fields)


DEFAULT = Policy("default", 30, 365)
BENCH = override(name="bench", robot="bench-1", warm_days=2, cold_days=5)
PRODUCTION = override(name="production", application="production", cold_days=335)


@pytest.fixture(autouse=True)
def no_fleet_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Settings come only from what each test sets (and auth stays off, as for every test)."""
    import os

    for name in list(os.environ):
        if name.startswith("FLEET_") and name != "FLEET_AUTH":
            monkeypatch.delenv(name)


# --- precedence ----------------------------------------------------------------------------------


def test_robot_override_beats_application_override_beats_default():
    # The application override is listed first: order does not decide, the kind of match does.
    policies = Policies(DEFAULT, (PRODUCTION, BENCH))
    bench = policies.for_run("bench-1", "production")
    assert bench == Policy("bench", 2, 5)
    assert bench.archive_after == dt.timedelta(days=2) and bench.delete_after == dt.timedelta(days=7)
    production = policies.for_run("prod-7", "production")
    assert production == Policy("production", 30, 335)  # warm_days left out: the default's
    assert production.delete_after == dt.timedelta(days=365)
    assert policies.for_run("prod-7", "fleet-test") is DEFAULT
    assert policies.for_run("bench-10", "Production") is DEFAULT  # exact, case-sensitive names
    assert Policies(DEFAULT).for_run("bench-1", "production") is DEFAULT


def test_first_override_for_the_same_robot_wins_and_missing_days_come_from_the_default():
    first = override(name="first", robot="r1", cold_days=0)
    second = override(name="second", robot="r1", warm_days=1, cold_days=1)
    policy = Policies(DEFAULT, (first, second)).for_run("r1", "app")
    assert policy == Policy("first", 30, 0)
    assert policy.delete_after == policy.archive_after  # cold_days = 0: warm straight to deleted


@pytest.mark.parametrize("targets", [{}, {"robot": "r1", "application": "app"}])
def test_an_override_names_exactly_one_of_robot_or_application(targets: dict[str, str]):
    with pytest.raises(ValidationError, match="must name exactly one of robot or application"):
        override(name="odd", warm_days=1, **targets)


@pytest.mark.parametrize("field", ["warm_days", "cold_days"])
def test_override_days_are_not_negative(field: str):
    with pytest.raises(ValidationError, match=field):
        override(name="neg", robot="r1", **{field: -1})
    with pytest.raises(ValidationError):
        override(robot="r1")  # a name is required: tombstones show it


# --- settings ------------------------------------------------------------------------------------


def test_policies_from_a_json_environment_variable(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    monkeypatch.setenv("FLEET_WARM_DAYS", "10")
    monkeypatch.setenv("FLEET_COLD_DAYS", "20")
    monkeypatch.setenv(
        "FLEET_RETENTION_POLICIES",
        json.dumps(
            [
                {"name": "bench", "robot": "bench-1", "warm_days": 2, "cold_days": 5},
                {"name": "production", "application": "production", "cold_days": 355},
            ]
        ),
    )
    policies = load_settings(data_dir=tmp_path).policies
    assert policies.default == Policy("default", 10, 20)
    assert policies.for_run("bench-1", "production") == Policy("bench", 2, 5)
    assert policies.for_run("prod-7", "production") == Policy("production", 10, 355)
    assert policies.for_run("prod-7", "other") == Policy("default", 10, 20)


@pytest.mark.parametrize(
    "bad",
    [
        [{"name": "both", "robot": "r", "application": "a"}],
        [{"name": "neither", "warm_days": 1}],
        [{"name": "negative", "robot": "r", "cold_days": -3}],
        {"name": "not-a-list", "robot": "r"},
    ],
)
def test_bad_policies_in_the_environment_are_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, bad: Any):
    monkeypatch.setenv("FLEET_RETENTION_POLICIES", json.dumps(bad))
    with pytest.raises(ValidationError, match="retention_policies"):
        load_settings(data_dir=tmp_path)


def test_a_misspelt_policy_field_is_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    """`cold_day = 7` must not quietly become the default's 365 days (the top-level settings forbid
    unknown names too)."""
    monkeypatch.setenv("FLEET_RETENTION_POLICIES", json.dumps([{"name": "bench", "robot": "r", "cold_day": 7}]))
    with pytest.raises(ValidationError, match="cold_day"):
        load_settings(data_dir=tmp_path)


TOML = """
warm_days = 14
cold_days = 100
restore_days = 3

[[retention_policies]]
name = "bench"
robot = "bench-1"
warm_days = 2
cold_days = 5

[[retention_policies]]
name = "production"
application = "production"
cold_days = 351
"""


def test_policies_from_toml_tables(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    config = tmp_path / "fleet.toml"
    config.write_text(TOML)
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    settings = load_settings(data_dir=tmp_path)
    assert settings.restore_days == 3
    assert settings.policies.default == Policy("default", 14, 100)
    assert [o.name for o in settings.retention_policies] == ["bench", "production"]
    assert settings.policies.for_run("bench-1", "production") == Policy("bench", 2, 5)
    assert settings.policies.for_run("prod-7", "production") == Policy("production", 14, 351)
    monkeypatch.setenv("FLEET_WARM_DAYS", "20")  # the environment wins over the file
    assert load_settings(data_dir=tmp_path).policies.for_run("prod-7", "production") == Policy("production", 20, 351)
    config.write_text(TOML + '\n[[retention_policies]]\nname = "both"\nrobot = "r"\napplication = "a"\n')
    with pytest.raises(ValidationError, match="exactly one of robot or application"):
        load_settings(data_dir=tmp_path)


@pytest.fixture
def app_from_toml(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[TestClient]:
    """The service's own wiring (`fleet serve`'s build) from a TOML file, as a test client."""
    config = tmp_path / "fleet.toml"
    config.write_text(TOML)
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    settings = load_settings(data_dir=tmp_path / "data", scheduler=False)
    engine = create_engine(settings.catalog_url)
    upgrade(engine)
    engine.dispose()
    built = build(settings)  # the node and its sides
    try:
        yield TestClient(create_app(built.node, built.ingest, built.retention))
    finally:
        built.node.hot.close()
        built.node.catalog.kw["bind"].dispose()


def test_get_retention_shows_the_default_and_each_override_resolved(app_from_toml: TestClient):
    body = app_from_toml.get("/v1/retention").json()
    assert body["policies"] == {
        "default": {"name": "default", "warm_days": 14, "cold_days": 100},
        "overrides": [
            {"name": "bench", "robot": "bench-1", "warm_days": 2, "cold_days": 5},
            {"name": "production", "application": "production", "warm_days": 14, "cold_days": 351},
        ],
    }
    assert body["restore_days"] == 3 and body["archive"] == "store"
    assert body["schedule"]["enabled"] is False


# --- applied to runs -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fleet_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A bench robot's run of the production application, a production robot's run, and a lab run."""
    root = tmp_path_factory.mktemp("policy-runs")
    made = {}
    for run, robot, application in (
        ("bench-run", "bench-1", "production"),
        ("prod-run", "prod-7", "production"),
        ("lab-run", "lab-3", "fleet-test"),
    ):
        made[run] = log_run(
            root / f"{run}.rrd", run, entities=2, frames=5, points=100, robot=robot, application=application, text=False
        )
    return made


def _planned(node: Node) -> list[tuple[str, str, str | None]]:
    return sorted((a.run_id, a.action, a.policy) for a in plan(node.retention))


def _run(client: TestClient, run: str) -> dict[str, Any]:
    got = client.get(f"/v1/runs/{run}")
    assert got.status_code == 200, got.text
    body: dict[str, Any] = got.json()
    return body


@pytest.mark.sdk
def test_bench_runs_expire_in_a_week_while_production_keeps_a_year(
    tiers: Tiers, make_node: NodeFactory, fleet_runs: dict[str, Path]
):
    node = make_node(tiers, clock=Clock(), warm_days=30, cold_days=30, overrides=(BENCH, PRODUCTION))
    start = node.clock.now
    for path in fleet_runs.values():
        node.upload(path)
    node.clock.advance(minutes=11)
    promotions = plan(node.retention, ["promote"])
    assert len(promotions) == 3 and all(o.ok for o in run_plan(node.retention, promotions))
    client = TestClient(create_app(node.context, node.ingest, node.retention))
    assert _run(client, "bench-run")["policy"] == {"name": "bench", "warm_days": 2, "cold_days": 5}
    assert _run(client, "prod-run")["policy"] == {"name": "production", "warm_days": 30, "cold_days": 335}
    assert _run(client, "lab-run")["policy"] == {"name": "default", "warm_days": 30, "cold_days": 30}

    def at(days: float) -> list[tuple[str, str, str | None]]:
        node.clock.now = start + dt.timedelta(days=days, minutes=1)
        planned = _planned(node)
        outcomes = retention_job(node.retention)
        assert outcomes is not None and all(o.ok for o in outcomes)
        return planned

    assert at(1) == []
    assert at(2) == [("bench-run", "archive", "bench")]
    assert at(7) == [("bench-run", "delete", "bench")]  # the same clock: production's runs stay
    bench = _run(client, "bench-run")
    assert bench["tier"] == "deleted" and bench["lifecycle"]["deleted_policy"] == "bench"
    assert _run(client, "prod-run")["tier"] == "warm" and _run(client, "lab-run")["tier"] == "warm"
    assert at(30) == [("lab-run", "archive", "default"), ("prod-run", "archive", "production")]
    assert at(60) == [("lab-run", "delete", "default")]
    assert at(364) == []
    assert _run(client, "prod-run")["tier"] == "cold"
    assert at(365) == [("prod-run", "delete", "production")]
    assert [_run(client, r)["lifecycle"]["deleted_policy"] for r in ("bench-run", "lab-run", "prod-run")] == [
        "bench",
        "default",
        "production",
    ]
    assert listing(tiers.warm) == [] and listing(tiers.cold) == []
