"""Finding runs by the corpus in the console (auth on, on each catalog): the runs list's metric, tag
and event filters give the runs `GET /v1/runs` gives, and the built-in dashboard "distance between
interventions" gives what an independent computation over the metrics gives, and what its SQL gives
on `POST /v1/sql`, following new runs at each look."""

from __future__ import annotations

import datetime as dt
import re
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

import pytest
from fastapi.testclient import TestClient

from catalog import corpus
from catalog.db import session_scope
from catalog.queries import save_run
from services.console.app import install
from services.console.interventions import Metrics, dashboard_sql
from tests.catalog.records import run_record
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.console.test_sessions import log_in

ROW = re.compile(r'<tr data-run="([^"]+)"')
CELL = re.compile(
    r'<tr data-week="([^"]+)" data-version="([^"]+)" data-runs="(\d+)" data-distance="([^"]+)"\s+'
    r'data-interventions="([^"]*)"\s+data-ratio="([^"]*)"'
)


@dataclass(frozen=True)
class Drive:
    """A run and the metrics its evaluation gave (None: no such metric)."""

    run_id: str
    started: dt.datetime
    distance: float | None
    interventions: float | None
    version: str | None
    tags: tuple[str, ...] = ()
    events: int = 0  # intervention events


# 2025-12-29 is a Monday in ISO week 2026-W01; 2026-01-05 starts W02.
DRIVES = (
    Drive("d-1", dt.datetime(2025, 12, 29, 8, tzinfo=dt.UTC), 1200.0, 3, "2.3.0", ("night-shift",), 3),
    Drive("d-2", dt.datetime(2026, 1, 2, 22, tzinfo=dt.UTC), 800.0, 1, "2.3.0", (), 1),
    Drive("d-3", dt.datetime(2026, 1, 1, 9, tzinfo=dt.UTC), 90.0, 0, "2.4.0", ("night-shift", "dock-2")),
    Drive("d-4", dt.datetime(2026, 1, 6, 9, tzinfo=dt.UTC), 300.0, 2, "2.4.0", ("dock-2",), 2),
    Drive("d-5", dt.datetime(2026, 1, 7, 9, tzinfo=dt.UTC), 150.5, None, None),  # no count, no version
    Drive("d-6", dt.datetime(2026, 1, 8, 9, tzinfo=dt.UTC), None, 4, "2.4.0", (), 4),  # no distance: left out
)


@pytest.fixture
def console(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url) as depot:
        install(depot.app)
        for drive in DRIVES:
            record(depot, drive)
        yield depot


def record(depot: Depot, drive: Drive) -> None:
    """The run in the catalog, with the metrics, tags and events an evaluation would give it."""
    metrics = [
        corpus.MetricFacts(name, value, None)
        for name, value in (("distance_m", drive.distance), ("interventions", drive.interventions))
        if value is not None
    ]
    if drive.version is not None:
        metrics.append(corpus.MetricFacts("sw_version", None, drive.version))
    events = [
        corpus.EventFacts("intervention", "warn", "frame", "sequence", i, i, corpus.RULE, "rule intervention@1")
        for i in range(drive.events)
    ]
    with session_scope(depot.app.state.catalog, write=True) as session:
        save_run(session, run_record(drive.run_id, at=drive.started, robot_id="robot-7"), drive.started)
        corpus.replace_evaluation(
            session,
            run_id=drive.run_id,
            robot_id="robot-7",
            rules_version=1,
            state="final",
            events=events,
            metrics=metrics,
            capped=False,
            note=None,
            now=drive.started,
        )
        corpus.add_tags(session, drive.run_id, drive.tags, "alice", drive.started)


def signed_in(depot: Depot) -> TestClient:
    return log_in(TestClient(depot.app), depot.token("read"))


# --- the runs list --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "query",
    [
        [("metric", "distance_m>100")],
        [("metric", "distance_m>100"), ("metric", "interventions<=1")],
        [("metric", "sw_version=2.4.0")],
        [("tag", "night-shift")],
        [("tag", "night-shift"), ("tag", "dock-2")],
        [("event", "intervention")],
        [("event", "intervention"), ("tag", "dock-2"), ("metric", "distance_m>=300")],
        [("metric", "distance_m>100"), ("sort", "-metric.distance_m")],
    ],
)
def test_the_runs_list_filters_by_metric_tag_and_event_as_the_api_does(
    console: Depot, query: list[tuple[str, str]]
) -> None:
    page = signed_in(console).get(f"/console/runs?{urlencode(query)}")
    assert page.status_code == 200, page.text
    shown = ROW.findall(page.text)
    answer = console.client.get(f"/v1/runs?{urlencode(query)}", headers=bearer(console.token("read")))
    assert answer.status_code == 200, answer.text
    assert shown == [run["id"] for run in answer.json()["runs"]]
    assert shown, "a filter that matches nothing proves nothing"
    for name, value in query:  # the filter stays in its box
        assert f'name="{name}" value="{value.replace(">", "&gt;").replace("<", "&lt;")}"' in page.text or name == "sort"


def test_a_bad_metric_filter_is_the_page_with_the_reason(console: Depot) -> None:
    page = signed_in(console).get("/console/runs?metric=distance_m~100")
    assert page.status_code == 400 and 'id="problem"' in page.text and "distance_m~100" in page.text
    assert not ROW.findall(page.text)


# --- the dashboard ------------------------------------------------------------------------------------

Cells = dict[tuple[str, str], tuple[int, float, float | None, float | None]]  # (week, version) -> numbers


def expected(drives: tuple[Drive, ...]) -> Cells:
    """Per (ISO week, version): runs, distance, interventions, distance per intervention, in Python."""
    groups: dict[tuple[str, str], list[Drive]] = defaultdict(list)
    for drive in drives:
        if drive.distance is None:
            continue
        year, week, _ = drive.started.isocalendar()
        groups[(f"{year}-W{week:02d}", drive.version or "(none)")].append(drive)
    out = {}
    for key, members in groups.items():
        distance = sum(d.distance or 0.0 for d in members)
        counted = [d.interventions for d in members if d.interventions is not None]
        interventions = float(sum(counted)) if counted else None
        ratio = distance / interventions if interventions else None
        out[key] = (len(members), distance, interventions, ratio)
    return out


def shown(page: str) -> Cells:
    def number(text: str) -> float | None:
        return float(text) if text else None

    return {
        (week, version): (int(runs), float(distance), number(count), number(ratio))
        for week, version, runs, distance, count, ratio in CELL.findall(page)
    }


def assert_same(got: Cells, want: Cells) -> None:
    """The same groups with the same numbers (to rounding; None where there is none)."""
    assert sorted(got) == sorted(want)
    for key, values in want.items():
        for have, wanted in zip(got[key], values, strict=True):
            assert (have is None) == (wanted is None) and (wanted is None or have == pytest.approx(wanted)), key


def test_the_dashboard_equals_an_independent_computation_and_its_sql(console: Depot) -> None:
    browser = signed_in(console)
    page = browser.get("/console/dashboards/interventions")
    assert page.status_code == 200, page.text
    want = expected(DRIVES)
    assert_same(shown(page.text), want)
    assert want[("2026-W01", "2.3.0")] == (2, 2000.0, 4.0, 500.0)  # the year's edge: one ISO week
    assert want[("2026-W01", "2.4.0")][3] is None  # no intervention: no ratio
    # The SQL shown on the page gives the same numbers on POST /v1/sql.
    sql = dashboard_sql(Metrics())
    assert sql.replace("'", "&#39;").replace("<", "&lt;").replace(">", "&gt;") in page.text
    answer = console.client.post("/v1/sql", json={"query": sql}, headers=bearer(console.token("read")))
    assert answer.status_code == 200, answer.text
    body = answer.json()
    names = [c["name"] for c in body["columns"]]
    assert names == ["iso_week", "sw_version", "runs", "distance", "interventions", "distance_per_intervention"]
    by_sql: Cells = {(row[0], row[1]): (row[2], row[3], row[4], row[5]) for row in body["rows"]}
    assert_same(by_sql, shown(page.text))

    # A run sealed since: the next look counts it.
    late = Drive("d-7", dt.datetime(2026, 1, 9, 9, tzinfo=dt.UTC), 700.0, 3, "2.4.0")
    record(console, late)
    again = shown(browser.get("/console/dashboards/interventions").text)
    assert_same(again, expected((*DRIVES, late)))
    assert again[("2026-W02", "2.4.0")] == (2, 1000.0, 5.0, 200.0)


def test_the_dashboard_says_which_metrics_it_uses_and_takes_others(console: Depot) -> None:
    browser = signed_in(console)
    page = browser.get("/console/dashboards/interventions")
    for css, name in (("distance", "distance_m"), ("interventions", "interventions"), ("version", "sw_version")):
        assert f'<code id="metric-{css}">{name}</code>' in page.text
    assert 'id="sql"' in page.text and "nullif(sum(interventions), 0)" in page.text
    other = browser.get("/console/dashboards/interventions?distance=km&interventions=stops&version=build")
    assert "d.name = &#39;km&#39;" in other.text and "i.name = &#39;stops&#39;" in other.text
    assert "v.name = &#39;build&#39;" in other.text
    bad = browser.get("/console/dashboards/interventions?distance=x%27%20OR%201%3D1")
    assert bad.status_code == 422 and "not a metric name" in bad.text and 'id="sql"' not in bad.text
    listed = browser.get("/console/dashboards")
    assert 'href="/console/dashboards/interventions"' in listed.text
    assert TestClient(console.app).get("/console/dashboards/interventions", follow_redirects=False).status_code == 303
