"""Events and tags over REST with auth on, through the REST client: people's annotations (times by
the timeline's type, refused when bad), events found with filters and a cursor, each with a viewer
link, and tags with who added each."""

from __future__ import annotations

import datetime as dt
from urllib.parse import parse_qs, urlsplit

import pytest

from catalog import corpus
from catalog.db import session_scope
from core.timefmt import timestamp
from services.corpus.links import PAD_NS
from tests.services.auth.conftest import Depot, bearer
from tests.services.corpus.conftest import T0, add_run, catalog_of, refused, sdk
from tests.services.rrd.recordings import Recording

NS = 1_000_000_000


def test_a_person_annotates_a_run(depot: Depot):
    add_run(depot, "run-a", robot="robot-7")
    alice = sdk(depot, depot.token("write", name="alice"))
    iso_start = timestamp(T0 + 2 * NS)
    made = alice.annotate(
        "run-a", "log_time", iso_start, end=str(T0 + 5 * NS), label="swerved", note="near dock 2", severity="warn"
    )
    assert made["id"].startswith("ev-") and len(made["id"]) == 19
    assert {k: made[k] for k in ("run_id", "robot_id", "kind", "severity", "timeline", "timeline_type")} == {
        "run_id": "run-a",
        "robot_id": "robot-7",
        "kind": "annotation",
        "severity": "warn",
        "timeline": "log_time",
        "timeline_type": "timestamp",
    }
    assert (made["start"], made["end"], made["start_iso"]) == (T0 + 2 * NS, T0 + 5 * NS, iso_start)
    assert (made["origin"], made["source"], made["label"], made["note"]) == (
        "person",
        "alice",
        "swerved",
        "near dock 2",
    )
    assert made["rules_version"] is None and made["created_at"].endswith("Z")
    ticks = alice.annotate("run-a", "frame", 40, end=45, kind="near_miss")
    assert (ticks["start"], ticks["end"], ticks["severity"], ticks["start_iso"]) == (40, 45, "info", None)
    instant = alice.annotate("run-a", "frame", "50")
    assert instant["start"] == instant["end"] == 50

    listed = sdk(depot, depot.token("read")).run_events("run-a")
    assert [e["id"] for e in listed] == [ticks["id"], instant["id"], made["id"]]  # by start
    assert listed[2] == {**made, "viewer_url": listed[2]["viewer_url"]}
    shown = sdk(depot, depot.token("read")).event(made["id"])
    assert {**shown, "viewer_url": None} == {**made, "viewer_url": None}


def test_annotations_with_bad_times_are_422_and_unknown_runs_404(depot: Depot):
    add_run(depot, "run-a")
    alice = sdk(depot, depot.token("write", name="alice"))
    refused(lambda: alice.annotate("run-a", "log_time", "yesterday"), 422, "parameter 'start'", "not a timestamp")
    refused(lambda: alice.annotate("run-a", "frame", "2026-11-21T08:00:00Z"), 422, "parameter 'start'", "sequence")
    refused(lambda: alice.annotate("run-a", "frame", 10, end="x"), 422, "parameter 'end'")
    refused(lambda: alice.annotate("run-a", "frame", 10, end=9), 422, "parameter 'end'", "before the start")
    refused(lambda: alice.annotate("run-a", "frame", str(2**64)), 422, "outside the range")
    refused(lambda: alice.annotate("run-a", "wall", 10), 422, "no timeline 'wall'", "frame, log_time")
    refused(lambda: alice.annotate("run-a", "frame", 10, severity="fatal"), 422, "parameter 'severity'")
    refused(lambda: alice.annotate("run-a", "frame", 10, kind="two words"), 422, "parameter 'kind'")
    refused(lambda: alice.annotate("run-a", "frame", 10, label="x" * 1001), 422, "parameter 'label'")
    refused(lambda: alice.annotate("no-such-run", "frame", 10), 404, "no run 'no-such-run'")
    odd = depot.client.post(
        "/v1/runs/run-a/events",
        json={"timeline": "frame", "start": 1, "colour": "red"},
        headers=bearer(depot.token("write")),
    )
    assert odd.status_code == 422
    boolean = depot.client.post(
        "/v1/runs/run-a/events", json={"timeline": "frame", "start": True}, headers=bearer(depot.token("write"))
    )
    assert boolean.status_code == 422
    assert sdk(depot, depot.token("read")).run_events("run-a") == []
    refused(lambda: sdk(depot, depot.token("read")).run_events("no-such-run"), 404, "no run")
    refused(lambda: sdk(depot, depot.token("read")).event("ev-0000000000000000"), 404, "no event")
    refused(lambda: sdk(depot, depot.token("read")).annotate("run-a", "frame", 1), 403, "needs the 'write' scope")


def _evaluation(depot: Depot, run_id: str, robot: str, kinds: list[tuple[str, str]], at: dt.datetime) -> None:
    """Rule- and robot-made events of a run, recorded at `at`."""
    facts = [
        corpus.EventFacts(
            kind=kind,
            severity=severity,
            timeline="log_time",
            timeline_type="timestamp",
            start=T0 + i * NS,
            end=T0 + i * NS + NS,
            origin=corpus.ROBOT if kind == "hard_brake" else corpus.RULE,
            source="robot" if kind == "hard_brake" else f"rule {kind}@1",
        )
        for i, (kind, severity) in enumerate(kinds)
    ]
    with session_scope(catalog_of(depot), write=True) as session:
        corpus.replace_evaluation(
            session,
            run_id=run_id,
            robot_id=robot,
            rules_version=1,
            state="final",
            events=facts,
            metrics=[],
            capped=False,
            note=None,
            now=at,
        )


def test_events_are_found_by_filters_a_page_at_a_time(depot: Depot):
    early, late = dt.datetime(2026, 11, 20, tzinfo=dt.UTC), dt.datetime(2026, 11, 22, tzinfo=dt.UTC)
    add_run(depot, "run-a", robot="robot-7")
    add_run(depot, "run-b", robot="robot-9")
    _evaluation(
        depot, "run-a", "robot-7", [("intervention", "warn"), ("intervention", "warn"), ("hard_brake", "error")], early
    )
    _evaluation(depot, "run-b", "robot-9", [("intervention", "warn"), ("stuck", "info")], late)
    alice = sdk(depot, depot.token("write", name="alice"))
    mine = alice.annotate("run-b", "frame", 3, label="look here", severity="error")
    reader = sdk(depot, depot.token("read"))

    def ids(**flt: object) -> list[str]:
        return [e["id"] for e in reader.events(**flt)["events"]]

    everything = reader.events()["events"]
    assert len(everything) == 6 and everything[0]["id"] == mine["id"]  # newest first
    assert [(e["created_at"], e["id"]) for e in everything] == sorted(
        ((e["created_at"], e["id"]) for e in everything), reverse=True
    )
    by_id = {e["id"]: e for e in everything}
    assert {by_id[i]["kind"] for i in ids(kind="intervention")} == {"intervention"} and len(
        ids(kind="intervention")
    ) == 3
    assert len(ids(kind=["intervention", "stuck"])) == 4
    assert {by_id[i]["robot_id"] for i in ids(robot="robot-9")} == {"robot-9"} and len(ids(robot="robot-9")) == 3
    assert {by_id[i]["run_id"] for i in ids(run="run-a")} == {"run-a"} and len(ids(run="run-a")) == 3
    assert ids(severity="error") and {by_id[i]["severity"] for i in ids(severity="error")} == {"error"}
    assert len(ids(severity="error")) == 2
    assert ids(source="alice") == [mine["id"]] and ids(origin="person") == [mine["id"]]
    assert [by_id[i]["kind"] for i in ids(source="robot")] == ["hard_brake"]
    assert len(ids(source="rule intervention@1")) == 3
    assert len(ids(since="2026-11-21")) == 3 and len(ids(until="2026-11-21")) == 3
    assert len(ids(since="2026-11-19", until="2026-11-21", kind="intervention", robot="robot-7")) == 2
    assert ids(kind="no-such-kind") == []
    assert by_id[ids(kind="hard_brake")[0]]["origin"] == "robot"

    pages, cursor = [], None
    while True:
        page = reader.events(limit=2, cursor=cursor)
        pages.append([e["id"] for e in page["events"]])
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert [i for p in pages for i in p] == [e["id"] for e in everything] and all(len(p) <= 2 for p in pages)
    filtered = reader.events(kind="intervention", limit=2)
    rest = reader.events(kind="intervention", limit=2, cursor=filtered["next_cursor"])
    assert [e["id"] for e in filtered["events"] + rest["events"]] == ids(kind="intervention")

    refused(lambda: reader.events(cursor="not-a-cursor"), 422, "parameter 'cursor'")
    refused(lambda: reader.events(severity="fatal"), 422, "parameter 'severity'")
    refused(lambda: reader.events(origin="alien"), 422, "parameter 'origin'")
    refused(lambda: reader.events(limit=0), 422, "parameter 'limit'")
    refused(lambda: reader.events(since="last week"), 422, "parameter 'since'")
    refused(lambda: sdk(depot, depot.token("ingest", robot="robot-7")).events(), 403, "needs the 'read' scope")


def test_each_event_links_to_its_window_padded_by_a_few_seconds(depot: Depot):
    add_run(depot, "run-a")
    alice_token = depot.token("write", name="alice")
    made = sdk(depot, alice_token).annotate("run-a", "log_time", str(T0 + 10 * NS), end=str(T0 + 12 * NS))
    url = urlsplit(made["viewer_url"])
    query = parse_qs(url.query)
    assert url.path == "/v1/runs/run-a/recording.rrd"
    assert (query["timeline"], query["start"], query["end"]) == (
        ["log_time"],
        [str(T0 + 10 * NS - PAD_NS)],
        [str(T0 + 12 * NS + PAD_NS)],
    )
    assert 2 * NS <= PAD_NS <= 10 * NS  # a few seconds
    assert "sig" in query and "expires" in query, query  # a signed link: auth is on
    assert alice_token not in made["viewer_url"]
    ticks = sdk(depot, alice_token).annotate("run-a", "frame", 7, end=9)
    assert parse_qs(urlsplit(ticks["viewer_url"]).query)["start"] == ["7"]


@pytest.mark.sdk
def test_an_events_link_opens_its_window_without_a_token(depot: Depot, recordings: dict[str, Recording]):
    writer = sdk(depot, depot.token("write", name="alice"))
    writer.upload(recordings["points"].path)
    run_id = recordings["points"].recordings[0]["recording_id"]
    made = writer.annotate(run_id, "frame", 101, end=102, label="the second frame")
    url = urlsplit(made["viewer_url"])
    opened = depot.client.get(f"{url.path}?{url.query}")  # no Authorization header: the link is the grant
    assert opened.status_code == 200, opened.text
    assert opened.content[:4] == b"RRF2"
    tampered = depot.client.get(f"{url.path}?{url.query.replace('start=101', 'start=100')}")
    assert tampered.status_code in (401, 403)


def test_tags_round_trip_with_who_added_each(depot: Depot):
    add_run(depot, "run-a")
    alice = sdk(depot, depot.token("write", name="alice"))
    bob = sdk(depot, depot.token("write", name="bob"))
    first = alice.tag("run-a", ["night-shift", "dock-2", "night-shift"])
    assert first["added"] == ["night-shift", "dock-2"]
    again = bob.tag("run-a", ["dock-2", "rain"])
    assert again["added"] == ["rain"]
    assert [(t["tag"], t["added_by"]) for t in again["tags"]] == [
        ("dock-2", "alice"),
        ("night-shift", "alice"),
        ("rain", "bob"),
    ]
    assert all(t["added_at"].endswith("Z") for t in again["tags"])
    untagged = bob.untag("run-a", ["dock-2", "never-there"])
    assert untagged["removed"] == ["dock-2"]
    assert [t["tag"] for t in untagged["tags"]] == ["night-shift", "rain"]
    by_body = depot.client.request(
        "DELETE", "/v1/runs/run-a/tags", json={"tags": ["rain"]}, headers=bearer(depot.token("write"))
    )
    assert by_body.status_code == 200 and by_body.json()["removed"] == ["rain"]
    assert [t["tag"] for t in by_body.json()["tags"]] == ["night-shift"]


@pytest.mark.parametrize("bad", ["", "two words", "a,b", "tab\there", "x" * 129, "nul\x00"])
def test_tags_are_checked(depot: Depot, bad: str):
    add_run(depot, "run-a")
    alice = sdk(depot, depot.token("write", name="alice"))
    refused(lambda: alice.tag("run-a", [bad]), 422, "parameter 'tags'")
    assert alice.tag("run-a", ["x" * 128])["added"] == ["x" * 128]


def test_tags_of_unknown_runs_and_without_write(depot: Depot):
    add_run(depot, "run-a")
    alice = sdk(depot, depot.token("write", name="alice"))
    refused(lambda: alice.tag("no-such-run", ["a"]), 404, "no run 'no-such-run'")
    refused(lambda: alice.untag("no-such-run", ["a"]), 404, "no run 'no-such-run'")
    refused(lambda: alice.tag("run-a", []), 422, "at least one tag")
    refused(lambda: alice.untag("run-a", []), 422, "at least one tag")
    reader = sdk(depot, depot.token("read"))
    refused(lambda: reader.tag("run-a", ["a"]), 403, "needs the 'write' scope")
    refused(lambda: reader.untag("run-a", ["a"]), 403, "needs the 'write' scope")
    assert depot.client.post("/v1/runs/run-a/tags", json={"tags": ["a"]}).status_code == 401
    missing_body = depot.client.post("/v1/runs/run-a/tags", json={}, headers=bearer(depot.token("write")))
    assert missing_body.status_code == 422
