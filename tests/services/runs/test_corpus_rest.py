"""Search over REST (auth on, both catalogs): `GET /v1/runs` with metric, tag and event filters and
a metric sort, its 4xx answers, and what `GET /v1/runs/RUN` shows of the corpus, hot runs included;
`fleet runs ls` asks the same."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from click.testing import CliRunner

from catalog import corpus
from catalog.corpus import MetricFacts
from catalog.db import session_scope
from sdk_client import rest
from services.cli.main import cli
from services.rrd.decoder import iter_events
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.ingest.feeding import feed
from tests.services.rrd.recordings import Recording
from tests.services.runs.corpus_scene import IDS, RULES_VERSION, T0, expected, write_scene


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url, catalog_flush_s=3600) as opened:
        with session_scope(opened.app.state.catalog, write=True) as session:
            write_scene(session)
        yield opened


def listed(depot: Depot, **params: Any) -> dict[str, Any]:
    answer = depot.client.get("/v1/runs", params=params, headers=bearer(depot.token("read")))
    assert answer.status_code == 200, answer.text
    found: dict[str, Any] = answer.json()
    return found


FILTERS: list[dict[str, Any]] = [
    {"metric": ["distance_m>100"]},
    {"metric": ["distance_m>=80", "distance_m!=150"]},
    {"metric": ["sw_version=2.3"]},
    {"tag": ["night-shift", "dock-2"]},
    {"event": ["intervention"]},
    {"metric": ["distance_m>=100"], "tag": ["dock-2"], "event": ["intervention"]},
]


def test_runs_are_filtered_by_metric_tag_and_event(depot: Depot):
    for flt in FILTERS:
        assert sorted(r["id"] for r in listed(depot, sort="id", **flt)["runs"]) == expected(flt), flt
    assert [r["id"] for r in listed(depot, metric="distance_m>100", sort="id")["runs"]] == ["r-1", "r-4"]


def test_runs_sort_by_a_metric_a_page_at_a_time(depot: Depot):
    seen, cursor = [], None
    while True:
        page = listed(depot, sort="-metric.distance_m", limit=2, **({"cursor": cursor} if cursor else {}))
        seen += [r["id"] for r in page["runs"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ["r-4", "r-1", "r-3", "r-2", "r-6", "r-5"]


@pytest.mark.parametrize(
    ("params", "name", "says"),
    [
        ({"metric": "distance_m"}, "metric", "NAME OP VALUE with OP one of > >= < <= = !="),
        ({"metric": "distance_m>far"}, "metric", "compares numbers"),
        ({"sort": "metric."}, "sort", "metric.NAME"),
        ({"sort": "size"}, "sort", "metric.NAME"),
        ({"sort": "metric.distance_m", "cursor": "W3RydWUsInItMSJd"}, "cursor", "not a cursor"),
        ({"tag": ["t"] * 33}, "tag", "at most 32"),
    ],
)
def test_bad_search_parameters_are_422(depot: Depot, params: dict[str, Any], name: str, says: str):
    answer = depot.client.get("/v1/runs", params=params, headers=bearer(depot.token("read")))
    assert answer.status_code == 422, answer.text
    assert answer.json()["code"] == "INVALID_ARGUMENT"
    assert f"parameter {name!r}" in answer.json()["message"] and says in answer.json()["message"]


def test_search_needs_the_read_scope(depot: Depot):
    assert depot.client.get("/v1/runs", params={"tag": "night-shift"}).status_code == 401
    robot = bearer(depot.token("ingest", robot="robot-a"))
    assert depot.client.get("/v1/runs", params={"tag": "night-shift"}, headers=robot).status_code == 403
    assert depot.client.get("/v1/runs/r-1", headers=robot).status_code == 403


def test_a_runs_answer_shows_its_metrics_tags_event_counts_and_evaluation(depot: Depot):
    run = depot.client.get("/v1/runs/r-1", headers=bearer(depot.token("read"))).json()
    assert run["metrics"] == {"distance_m": 150.0, "sw_version": "2.3"}
    assert run["metrics_rules_version"] == RULES_VERSION
    assert run["tags"] == [
        {"tag": "dock-2", "added_by": "robot", "added_at": "2026-11-01T08:00:00Z"},
        {"tag": "night-shift", "added_by": "alice", "added_at": "2026-11-01T08:00:00Z"},
    ]
    assert run["event_counts"] == {"intervention": 2}
    assert run["evaluation"] == {
        "rules_version": RULES_VERSION,
        "state": "final",
        "events_capped": False,
        "note": None,
        "evaluated_at": "2026-11-01T08:00:00Z",
    }
    assert isinstance(run["events"], list)  # the retention log keeps its name
    capped = depot.client.get("/v1/runs/r-6", headers=bearer(depot.token("read"))).json()
    assert capped["evaluation"]["events_capped"] and "stopped at 1 event" in capped["evaluation"]["note"]
    assert capped["event_counts"] == {"hard_brake": 1, "stuck": 1} and capped["metrics"] == {"temp_c": 21.0}
    person = depot.client.get("/v1/runs/r-5", headers=bearer(depot.token("read"))).json()
    assert person["metrics"] == {} and person["metrics_rules_version"] is None
    assert person["event_counts"] == {"intervention": 1}


@pytest.mark.sdk
def test_a_hot_run_the_catalog_has_no_row_of_shows_its_corpus(depot: Depot, recordings: dict[str, Recording]):
    ingest = depot.app.state.ingest
    source = ingest.open_source(live=True)
    feed(ingest, source, iter_events(recordings["points"].path))  # still open: no catalog row yet
    run_id = "rec-points"
    with session_scope(depot.app.state.catalog, write=True) as session:  # as live rules write it
        corpus.replace_evaluation(
            session,
            run_id=run_id,
            robot_id="robot-7",
            rules_version=1,
            state="live",
            events=[],
            metrics=[MetricFacts("distance_m", 12.5, None)],
            capped=False,
            note=None,
            now=T0 + dt.timedelta(days=1),
        )
        corpus.add_tags(session, run_id, ["night-shift"], "alice", T0)
    run = depot.client.get(f"/v1/runs/{run_id}", headers=bearer(depot.token("read"))).json()
    assert (run["tier"], run["status"]) == ("hot", "live")
    assert run["metrics"] == {"distance_m": 12.5} and run["evaluation"]["state"] == "live"
    assert [t["tag"] for t in run["tags"]] == ["night-shift"] and run["event_counts"] == {}


def test_fleet_runs_ls_filters_and_sorts_as_rest_does(depot: Depot, monkeypatch: pytest.MonkeyPatch):
    transport = depot.client._transport  # the app in process, under the CLI's client
    real = rest.FleetClient.__init__

    def in_process(self: rest.FleetClient, *args: Any, **kwargs: Any) -> None:
        real(self, *args, **kwargs)
        self._http = httpx.Client(base_url="http://testserver", transport=transport, headers=self._http.headers)

    monkeypatch.setattr(rest.FleetClient, "__init__", in_process)
    monkeypatch.setenv("FLEET_TOKEN", depot.token("read"))
    args = ["runs", "ls", "--json", "--metric", "distance_m>=100", "--tag", "dock-2", "--sort", "-metric.distance_m"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert [r["id"] for r in json.loads(result.output)["runs"]] == ["r-4", "r-1"]
    assert len(IDS) == 6  # the others are there, and left out
