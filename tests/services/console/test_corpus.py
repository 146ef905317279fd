"""The corpus in the console (auth on, on each catalog): a run's events, metrics and tags on its
page (events marked on the coverage, each opening the viewer at its window), tags and annotations
edited with `write` and refused without it, and the Events page's filters and paging, and where each
event's window is, with a writer's button that pulls one left on the robot."""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pytest
from fastapi.testclient import TestClient

from catalog import corpus
from catalog.db import session_scope
from catalog.queries import TimelineRecord, save_run
from services.console.app import install
from tests.catalog.records import run_record
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.console.test_sessions import log_in
from tests.services.rrd.recordings import Recording

RUN = "rec-points"  # the points scene: timelines frame (sequence 100..105), sim (duration), log_time
CSRF = re.compile(r'name="csrf" value="([^"]+)"')
MARK = re.compile(r'<a href="([^"]+)" class="event-mark" data-event="([^"]+)">')
AT = dt.datetime(2026, 11, 23, 9, 0, tzinfo=dt.UTC)


@pytest.fixture
def console(tmp_path: Path, fresh_catalog_url: str, recordings: dict[str, Recording]) -> Iterator[Depot]:
    """A depot with the console, holding the points scene as a run."""
    with open_depot(tmp_path, fresh_catalog_url) as depot:
        install(depot.app)
        writer = bearer(depot.token("write"))
        uploaded = depot.client.post("/v1/uploads", content=recordings["points"].data, headers=writer)
        assert uploaded.status_code == 200, uploaded.text
        yield depot


def signed_in(depot: Depot, *scopes: str, name: str | None = None) -> TestClient:
    """A browser of its own (cookies), logged in with a token of `scopes`."""
    return log_in(TestClient(depot.app), depot.token(*scopes, name=name))


def csrf(page: str) -> str:
    found = CSRF.search(page)
    assert found, "the page has no form"
    return found.group(1)


def evaluate(depot: Depot, run_id: str, robot: str = "robot-7", *, severity: str = "warn", count: int = 2) -> None:
    """Rule-made events on `frame` and a log_time instant, and metrics, as an evaluation writes them."""
    rule = "rule intervention@1"
    events = [
        corpus.EventFacts("intervention", severity, "frame", "sequence", 100 + i, 101 + i, corpus.RULE, rule)
        for i in range(count)
    ]
    at = 10**18
    brake = corpus.EventFacts("hard_brake", "error", "log_time", "timestamp", at, at, corpus.ROBOT, "robot", "!")
    events.append(brake)
    metrics = [corpus.MetricFacts("distance_m", 12.5, None), corpus.MetricFacts("sw_version", None, "2.3.0")]
    with session_scope(depot.app.state.catalog, write=True) as session:
        corpus.replace_evaluation(
            session,
            run_id=run_id,
            robot_id=robot,
            rules_version=1,
            state="final",
            events=events,
            metrics=metrics,
            capped=False,
            note=None,
            now=AT,
        )
        corpus.add_tags(session, run_id, ["dock-2"], corpus.ROBOT_TAGGER, AT)


def tags_of(depot: Depot, run_id: str) -> dict[str, str]:
    with session_scope(depot.app.state.catalog) as session:
        return {t.tag: t.added_by for t in corpus.tags_of(session, run_id)}


def person_events(depot: Depot, run_id: str) -> list[tuple[str, str, int, int, str, str]]:
    with session_scope(depot.app.state.catalog) as session:
        return [
            (e.kind, e.timeline, e.range_start, e.range_end, e.label, e.source)
            for e in corpus.events_of_run(session, run_id)
            if e.origin == corpus.PERSON
        ]


# --- the run page -----------------------------------------------------------------------------------


def test_the_run_page_shows_events_metrics_and_tags_and_a_reader_gets_no_forms(console: Depot) -> None:
    robot = console.client.get(f"/v1/runs/{RUN}", headers=bearer(console.token("read"))).json()["robot_id"]
    evaluate(console, RUN, robot)
    browser = signed_in(console, "read")
    page = browser.get(f"/console/runs/{RUN}")
    assert page.status_code == 200, page.text

    api = console.client.get(f"/v1/runs/{RUN}/events", headers=bearer(console.token("read"))).json()["events"]
    assert len(api) == 3
    for event in api:  # each listed with kind, severity, source and label, and a link to its window
        row = re.search(rf'<tr data-event="{event["id"]}"[^>]*>(.*?)</tr>', page.text, re.S)
        assert row, event
        assert all(str(event[k]) in row.group(1) for k in ("kind", "severity", "source", "label"))
    assert 'data-metric="distance_m"' in page.text and "12.5" in page.text and "v1" in page.text
    assert 'data-metric="sw_version"' in page.text and "2.3.0" in page.text
    assert re.search(r'data-tag="dock-2">.*?by robot', page.text, re.S)
    assert 'id="evaluation" data-state="final"' in page.text

    # The coverage marks the events on its timeline, each opening the viewer at its padded window.
    timeline = re.search(r"Timeline coverage on <code>([^<]+)</code>", page.text)
    assert timeline
    marks = {ident: href.replace("&amp;", "&") for href, ident in MARK.findall(page.text)}
    on_it = [e for e in api if e["timeline"] == timeline.group(1)]
    assert on_it and set(marks) == {e["id"] for e in on_it}
    for event in on_it:
        link = urlsplit(marks[event["id"]])
        assert link.path == f"/console/runs/{RUN}/viewer"
        pad = 0 if event["timeline_type"] == "sequence" else 5_000_000_000
        window = {k: v[0] for k, v in parse_qs(link.query).items()}
        assert window == {
            "timeline": event["timeline"],
            "start": str(event["start"] - pad),
            "end": str(event["end"] + pad),
        }

    # A reader sees no edit form, and its posts (with a valid CSRF value) are refused and change nothing.
    assert "annotate-form" not in page.text and "tag-form" not in page.text and "untag" not in page.text
    token = csrf(page.text)
    for path, data in (
        ("tags", {"tags": "night-shift"}),
        ("tags/remove", {"tag": "dock-2"}),
        ("annotate", {"timeline": "frame", "start": "101", "label": "x"}),
    ):
        refused = browser.post(f"/console/runs/{RUN}/{path}", data={"csrf": token, **data}, follow_redirects=False)
        assert refused.status_code == 403, (path, refused.text)
    assert tags_of(console, RUN) == {"dock-2": "robot"}
    assert person_events(console, RUN) == []


def test_a_writer_tags_untags_and_annotates_from_the_run_page(console: Depot) -> None:
    browser = signed_in(console, "write", name="alice")
    page = browser.get(f"/console/runs/{RUN}")
    assert page.status_code == 200
    assert all(form in page.text for form in ('id="annotate-form"', 'id="tag-form"'))
    token = csrf(page.text)

    added = browser.post(f"/console/runs/{RUN}/tags", data={"csrf": token, "tags": "night-shift, dock-2"})
    assert added.status_code == 200 and 'id="notice"' in added.text
    assert tags_of(console, RUN) == {"night-shift": "alice", "dock-2": "alice"}
    assert re.search(r'data-tag="night-shift">.*?by alice.*?class="link untag"', added.text, re.S)
    removed = browser.post(f"/console/runs/{RUN}/tags/remove", data={"csrf": token, "tag": "dock-2"})
    assert removed.status_code == 200 and tags_of(console, RUN) == {"night-shift": "alice"}

    annotated = browser.post(
        f"/console/runs/{RUN}/annotate",
        data={"csrf": token, "timeline": "frame", "start": "101", "end": "103", "label": "robot hesitated"},
    )
    assert annotated.status_code == 200, annotated.text
    assert person_events(console, RUN) == [("annotation", "frame", 101, 103, "robot hesitated", "alice")]
    assert "robot hesitated" in annotated.text

    # Bad input is the page with its status and the reason; nothing is added.
    for data, said in (
        ({"timeline": "frame", "start": "103", "end": "101"}, "before the start"),
        ({"timeline": "nope", "start": "1"}, "has no timeline"),
        ({"timeline": "frame", "start": "soon"}, "not a sequence value"),
    ):
        bad = browser.post(f"/console/runs/{RUN}/annotate", data={"csrf": token, **data})
        assert bad.status_code == 422 and said in bad.text, (data, bad.text[:300])
    bad_tag = browser.post(f"/console/runs/{RUN}/tags", data={"csrf": token, "tags": " "})
    assert bad_tag.status_code == 422
    assert len(person_events(console, RUN)) == 1 and tags_of(console, RUN) == {"night-shift": "alice"}
    # Without the CSRF value, or on a run that is not there: refused.
    assert browser.post(f"/console/runs/{RUN}/tags", data={"tags": "x"}).status_code == 403
    assert browser.post("/console/runs/no-such-run/tags", data={"csrf": token, "tags": "x"}).status_code == 404


def test_the_viewer_page_opens_an_events_window(console: Depot) -> None:
    browser = signed_in(console, "read")
    page = browser.get(f"/console/runs/{RUN}/viewer?timeline=frame&start=101&end=103")
    assert page.status_code == 200
    signed = re.search(r'data-url="([^"]+)"', page.text) or re.search(r"rerun &#34;([^&]+)", page.text)
    assert signed
    query = parse_qs(urlsplit(signed.group(1).replace("&amp;", "&")).query)
    assert query["timeline"] == ["frame"] and query["start"] == ["101"] and query["end"] == ["103"]
    assert 'id="viewer-window"' in page.text
    assert browser.get(f"/console/runs/{RUN}/viewer?timeline=nope&start=1").status_code == 422
    assert browser.get(f"/console/runs/{RUN}/viewer?timeline=frame&start=5&end=1").status_code == 422


# --- the Events page ---------------------------------------------------------------------------------


def _event_rows(page: str) -> list[dict[str, str]]:
    rows = re.findall(
        r'<tr data-event="([^"]+)" data-kind="([^"]+)" data-robot="([^"]+)" data-run="([^"]+)" '
        r'data-severity="([^"]+)" data-source="([^"]+)"',
        page,
    )
    return [dict(zip(("id", "kind", "robot", "run", "severity", "source"), row, strict=True)) for row in rows]


def test_the_events_page_filters_and_pages_like_the_api(console: Depot) -> None:
    with session_scope(console.app.state.catalog, write=True) as session:
        for run_id, robot in (("run-a", "robot-a"), ("run-b", "robot-b")):
            timelines = [TimelineRecord("frame", "sequence", 0, 100)]
            save_run(session, run_record(run_id, robot_id=robot, timelines=timelines), AT)
    evaluate(console, "run-a", "robot-a", severity="warn", count=30)
    evaluate(console, "run-b", "robot-b", severity="info", count=30)
    browser = signed_in(console, "read")
    reader = bearer(console.token("read"))

    page = browser.get("/console/events")
    assert page.status_code == 200 and 'aria-current="page">Events' in page.text
    shown = _event_rows(page.text)
    assert len(shown) == 50 and 'id="next-page"' in page.text  # a page of 50
    listed = console.client.get("/v1/events?limit=50", headers=reader).json()
    assert [r["id"] for r in shown] == [e["id"] for e in listed["events"]]
    more = re.search(r'href="([^"]+)" id="next-page"', page.text)
    assert more
    rest = _event_rows(browser.get(more.group(1).replace("&amp;", "&")).text)
    assert {r["id"] for r in shown}.isdisjoint(r["id"] for r in rest) and len(shown) + len(rest) == 62

    for query, api_query in (
        ("kind=hard_brake", "kind=hard_brake"),
        ("robot=robot-b", "robot=robot-b"),
        ("severity=warn", "severity=warn"),
        ("source=robot", "source=robot"),
        ("kind=intervention&robot=robot-a&severity=warn", "kind=intervention&robot=robot-a&severity=warn"),
    ):
        rows = _event_rows(browser.get(f"/console/events?{query}").text)
        expected = console.client.get(f"/v1/events?{api_query}&limit=50", headers=reader).json()["events"]
        assert rows and [r["id"] for r in rows] == [e["id"] for e in expected], query
    rows = _event_rows(browser.get("/console/events?kind=hard_brake").text)
    assert {r["run"] for r in rows} == {"run-a", "run-b"} and {r["source"] for r in rows} == {"robot"}
    one = browser.get("/console/events?kind=hard_brake&robot=robot-a").text
    assert 'href="/console/runs/run-a"' in one  # to its run, and to the viewer at its window
    window = "timeline=log_time&amp;start=999999995000000000&amp;end=1000000005000000000"
    assert f"/console/runs/run-a/viewer?{window}" in one

    empty = browser.get("/console/events?kind=nothing-like-it")
    assert empty.status_code == 200 and 'id="no-events"' in empty.text
    bad = browser.get("/console/events?severity=loud")
    assert bad.status_code == 422 and "severity" in bad.text
    assert browser.get("/console/events?cursor=not-one").status_code == 422
    # Without a session: to the login page.
    assert TestClient(console.app).get("/console/events", follow_redirects=False).status_code == 303


def _held_event(console: Depot) -> str:
    """A trigger the run's robot fired and held on the robot (over its budget); its event's id."""
    body = {
        "pull_id": "pull-00000000be1d",
        "rules_version": 1,
        "event": {"kind": "slow", "severity": "warn", "timeline": "frame", "timeline_type": "sequence",
                  "start": 102, "end": 102},
        "window": {"timeline": "frame", "start": "100", "end": "105", "include": ["/points/**"]},
        "priority": "normal", "state": "held", "error": "over budget: 0 bytes left today",
    }  # fmt: skip
    reported = console.client.post(f"/v1/runs/{RUN}/triggered", json=body, headers=bearer(console.token("write")))
    assert reported.status_code == 201, reported.text
    return str(reported.json()["event"]["id"])


def _data_cell(page: str, event_id: str) -> str:
    row = re.search(rf'<tr data-event="{event_id}".*?</tr>', page, re.S)
    assert row, f"no row of {event_id}"
    return row.group(0)


def test_the_events_page_says_where_a_window_is_and_a_writer_pulls_it(console: Depot) -> None:
    event_id = _held_event(console)
    reader = signed_in(console, "read")
    row = _data_cell(reader.get("/console/events").text, event_id)
    assert 'data-state="held on robot: over budget"' in row and "pull-00000000be1d: trigger, held" in row
    assert "over budget: 0 bytes left today" in row and "Pull it" not in row  # no button for a reader
    refused = reader.post(f"/console/events/{event_id}/pull", data={"csrf": csrf(reader.get("/console").text)})
    assert refused.status_code == 403 and "write" in refused.text

    alice = signed_in(console, "write", name="alice")
    page = alice.get("/console/events?kind=slow")
    row = _data_cell(page.text, event_id)
    assert f'action="/console/events/{event_id}/pull"' in row
    assert alice.post(f"/console/events/{event_id}/pull", data={"back": "/console/events"}).status_code == 403
    token = csrf(page.text)
    pulled = alice.post(
        f"/console/events/{event_id}/pull",
        data={"csrf": token, "back": "/console/events?kind=slow"},
        follow_redirects=False,
    )
    assert pulled.status_code == 303 and pulled.headers["location"] == "/console/events?kind=slow&done=pulled"
    after = alice.get(pulled.headers["location"])
    assert 'id="notice"' in after.text
    row = _data_cell(after.text, event_id)
    assert 'data-state="pending"' in row and "alice" not in row and "Pull it" not in row
    pulls = console.client.get(f"/v1/runs/{RUN}/pulls", headers=bearer(console.token("read"))).json()["pulls"]
    assert (pulls[0]["origin"], pulls[0]["requested_by"], pulls[0]["event_id"]) == ("person", "alice", event_id)
    again = alice.post(
        f"/console/events/{event_id}/pull",
        data={"csrf": token, "back": "https://elsewhere.example/"},
        follow_redirects=False,
    )
    assert again.headers["location"] == "/console/events?done=pull-pending"  # never off the console's page
    annotated = alice.post(f"/console/runs/{RUN}/annotate", data={"csrf": token, "timeline": "frame", "start": "101"})
    assert annotated.status_code == 200
    (annotation,) = [e["id"] for e in corpus_events(console) if e["origin"] == "person"]
    no_window = alice.post(f"/console/events/{annotation}/pull", data={"csrf": token})
    assert no_window.status_code == 409 and "pulled by no trigger" in no_window.text


def corpus_events(console: Depot) -> list[dict[str, object]]:
    found: list[dict[str, object]] = console.client.get("/v1/events", headers=bearer(console.token("read"))).json()[
        "events"
    ]
    return found
