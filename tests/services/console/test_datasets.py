"""Dataset snapshots in the console (auth on, on each catalog): every snapshot with its latest version,
a snapshot's versions newest first, and a version with its selection, its skipped runs and its
episodes a page at a time, each as `GET /v1/datasets...` answers it: windows written as times on a
timestamp timeline, links to the episode's run and event, and the web viewer opened at its window
(a whole run's episode: the run). Unknown names and versions are the console's 404 page; hostile
selections are shown, never run as HTML."""

from __future__ import annotations

import datetime as dt
import html
import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import pytest
from fastapi.testclient import TestClient

from catalog import datasets as queries
from catalog.db import session_scope
from catalog.models import DatasetEpisode, DatasetSnapshot, DatasetVersion
from core.timefmt import timeline_value
from sdk_client.rest import FleetClient
from services.console import datasets as console_datasets
from services.console.app import install
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.console.test_sessions import log_in
from tests.services.corpus.conftest import sdk
from tests.services.datasets.conftest import upload, writer
from tests.services.rrd.recordings import Recording

RUN = "rec-points"  # the points scene: timelines frame (sequence), sim (duration), log_time (timestamp)
ROW = re.compile(
    r'<tr data-episode="(\d+)" data-run="([^"]*)" data-split="([^"]*)" data-missing="(\w+)"[^>]*>(.*?)</tr>', re.S
)
HREF = re.compile(r'class="([\w-]+)" href="([^"]+)"')
HOSTILE = '</pre><script>alert("x")</script><img src=x onerror=alert(1)>'


@pytest.fixture
def console(tmp_path: Path, fresh_catalog_url: str, recordings: dict[str, Recording]) -> Iterator[Depot]:
    """A depot with the console, holding the points scene (by a person's upload) and two synthetic
    runs of robot-7 on `frame`."""
    with open_depot(tmp_path, fresh_catalog_url) as depot:
        install(depot.app)
        uploaded = depot.client.post(
            "/v1/uploads", content=recordings["points"].data, headers=bearer(depot.token("write"))
        )
        assert uploaded.status_code == 200, uploaded.text
        upload(depot, "run-a", seal=True)
        upload(depot, "run-b")
        yield depot


def signed_in(depot: Depot, scope: str = "read") -> TestClient:
    return log_in(TestClient(depot.app), depot.token(scope))


def page(browser: TestClient, path: str, status: int = 200) -> str:
    answer = browser.get(path, follow_redirects=False)
    assert answer.status_code == status, answer.text[:2000]
    assert answer.headers["content-type"].startswith("text/html")
    text: str = answer.text
    return text


def episode_rows(text: str) -> list[dict[str, Any]]:
    """The episodes table as the page shows it: each row's attributes, cells and links."""
    rows = []
    for index, run_id, split, missing, body in ROW.findall(text):
        cells = [
            html.unescape(re.sub(r"<[^>]+>", "", c)).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", body, re.S)
        ]
        links = {cls: html.unescape(href) for cls, href in HREF.findall(body)}
        rows.append(
            {
                "index": int(index),
                "run": run_id,
                "split": split,
                "missing": missing == "true",
                "cells": cells,
                "links": links,
            }
        )
    return rows


def log_time_of(reader: FleetClient) -> tuple[int, int]:
    span = next(t for t in reader.run(RUN)["timelines"] if t["name"] == "log_time")
    assert span["type"] == "timestamp"
    return int(span["min"]), int(span["max"])


# --- the list and a snapshot's versions -------------------------------------------------------------------


def test_the_list_shows_each_snapshot_with_its_latest_version_as_the_api_does(console: Depot) -> None:
    alice = writer(console)
    alice.create_dataset("picks", robot=["robot-7"])
    alice.create_dataset("picks", robot=["robot-7"], split={"train": 0.5, "val": 0.5}, seed=3)
    alice.create_dataset("all-runs")
    browser = signed_in(console)
    text = page(browser, "/console/datasets")
    assert '<a href="/console/datasets" aria-current="page">Datasets</a>' in text  # the header's menu
    assert '<a href="/console/datasets"' in page(browser, "/console/runs")  # on every page

    listed = sdk(console, console.token("read")).datasets()
    rows = re.findall(r'<tr data-dataset="([^"]+)" data-ref="([^"]+)">(.*?)</tr>', text, re.S)
    assert [(name, ref) for name, ref, _ in rows] == [(d["name"], d["latest"]["ref"]) for d in listed]
    assert [ref for _, ref, _ in rows] == ["all-runs@1", "picks@2"]
    for (name, _, body), d in zip(rows, listed, strict=True):
        latest = d["latest"]
        assert f'<a class="dataset" href="/console/datasets/{name}">{name}</a>' in body
        assert f'<a class="ref" href="/console/datasets/{name}/{latest["version"]}">{latest["ref"]}</a>' in body
        assert f"<td>{latest['created_by']}</td>" in body and " UTC</td>" in body
        assert f'<td class="num">{latest["episodes"]}</td>' in body and f'<td class="num">{latest["runs"]}</td>' in body
        assert f'title="{latest["bytes"]:,} bytes"' in body
        for split, counts in latest["splits"].items():
            shown = re.search(
                rf'<li data-split="{split}"><strong>{split}</strong> (\d+) runs? · (\d+) episodes?</li>', body
            )
            assert shown and (int(shown[1]), int(shown[2])) == (counts["runs"], counts["episodes"])
    assert "no split" in rows[0][2] and "no split" not in rows[1][2]

    empty = open_empty(console)
    assert 'id="no-datasets"' in page(empty, "/console/datasets")


def open_empty(depot: Depot) -> TestClient:
    """A reader on a depot whose snapshots are all gone (the tables emptied): the list says how to make one."""
    with session_scope(depot.app.state.catalog, write=True) as session:
        for model in (DatasetEpisode, DatasetVersion, DatasetSnapshot):
            session.query(model).delete()
    return signed_in(depot)


def test_a_snapshots_page_lists_its_versions_newest_first(console: Depot) -> None:
    alice = writer(console)
    alice.create_dataset("picks", robot=["robot-7"], tag=["nothing-has-it"])
    alice.create_dataset("picks", robot=["robot-7"])
    browser = signed_in(console)
    text = page(browser, "/console/datasets/picks")
    answer = sdk(console, console.token("read")).dataset("picks")
    versions = re.findall(r'<tr data-version="(\d+)" data-ref="([^"]+)">(.*?)</tr>', text, re.S)
    assert [(int(n), ref) for n, ref, _ in versions] == [(v["version"], v["ref"]) for v in answer["versions"]]
    assert [int(n) for n, _, _ in versions] == [2, 1]
    for (number, _, body), v in zip(versions, answer["versions"], strict=True):
        assert f'href="/console/datasets/picks/{number}"' in body
        assert f'<td class="num">{v["episodes"]}</td>' in body and f'<td class="num">{v["chunks"]}</td>' in body
    assert 'id="dataset-made">First made by alice' in text
    assert '<a href="/console/datasets" aria-current="page">Datasets</a>' in text


# --- a version -------------------------------------------------------------------------------------------


def test_a_version_shows_its_selection_and_episodes_each_opening_the_viewer_at_its_window(console: Depot) -> None:
    alice = writer(console)
    low, high = log_time_of(alice)
    middle = (low + high) // 2
    made = alice.annotate(RUN, "log_time", middle, end=middle + 1000, kind="grasp", label="took it")
    alice.create_dataset("grasps", event_window={"event": ["grasp"], "before_s": 1, "after_s": 2}, fps=10)
    browser = signed_in(console)
    text = page(browser, "/console/datasets/grasps/1")
    api = alice.dataset_version("grasps", 1)

    shown = re.search(r'<pre id="selection">(.*?)</pre>', text, re.S)
    assert shown and json.loads(html.unescape(shown[1])) == api["selection"]
    assert html.unescape(shown[1]) == json.dumps(api["selection"], indent=2, sort_keys=True)
    assert 'id="ref">grasps@1</code>' in text and 'id="created-by">alice</dd>' in text
    assert 'id="rules-version">none running</dd>' in text and 'id="no-skipped"' in text

    (episode,) = api["episodes_page"]
    (row,) = episode_rows(text)
    assert (row["index"], row["run"], row["missing"]) == (0, RUN, False)
    assert episode["start"] == middle - 1_000_000_000 and episode["end"] == middle + 1000 + 2_000_000_000
    start, end = (timeline_value("timestamp", episode[k]) for k in ("start", "end"))
    assert start.endswith("Z") and row["cells"][5:7] == [start, end]  # times, as the events page shows them
    assert row["cells"][1:5] == [RUN, episode["robot_id"], "-", "log_time"]
    assert row["cells"][7] == "open in viewer" and row["cells"][8] == made["id"]
    assert row["cells"][9] == str(episode["chunks"])

    assert row["links"]["episode-run"] == f"/console/runs/{RUN}"
    assert row["links"]["episode-event"] == f"/console/runs/{RUN}#event-{made['id']}"
    assert f'id="event-{made["id"]}"' in page(browser, f"/console/runs/{RUN}")  # the event's row is the anchor
    viewer = urlsplit(row["links"]["episode-view"])
    assert viewer.path == f"/console/runs/{RUN}/viewer"
    window = {k: v[0] for k, v in parse_qs(viewer.query).items()}
    assert window == {"timeline": "log_time", "start": str(episode["start"]), "end": str(episode["end"])}
    opened = page(browser, row["links"]["episode-view"])  # the viewer signs the recording's link with it
    signed = re.search(r'data-url="([^"]+)"', opened) or re.search(r"rerun &#34;([^&]+)", opened)
    assert signed
    query = parse_qs(urlsplit(html.unescape(signed[1])).query)
    assert (query["timeline"], query["start"], query["end"]) == (["log_time"], [window["start"]], [window["end"]])

    # The marked places for what others add: quality flags per episode, and export jobs.
    assert '<th class="quality">Quality</th>' in text and 'class="quality" data-episode-quality>' in text
    assert '<section class="card" id="exports">' in text and 'id="no-exports"' in text
    assert '<a href="/console/datasets/grasps" id="dataset-link">grasps</a>' in text


def test_a_whole_run_episode_opens_the_run_and_a_deleted_runs_episode_says_why(console: Depot) -> None:
    alice = writer(console)
    alice.create_dataset("drives", robot=["robot-7"], split={"train": 0.5, "val": 0.5}, seed=1)
    admin = sdk(console, console.token("admin"))
    admin.delete_run("run-a", force=True)
    browser = signed_in(console)
    text = page(browser, "/console/datasets/drives/1")
    api = alice.dataset_version("drives", 1)["episodes_page"]
    rows = episode_rows(text)
    assert [(r["index"], r["run"], r["split"], r["missing"]) for r in rows] == [
        (e["index"], e["run_id"], e["split"], e["missing"]) for e in api
    ]
    by_run = {r["run"]: r for r in rows}
    gone, kept = by_run["run-a"], by_run["run-b"]
    assert gone["run"] == "run-a" and gone["missing"] and "episode-view" not in gone["links"]
    assert gone["cells"][5:7] == ["whole run", ""] and gone["cells"][10].startswith("missing run deleted on ")
    assert gone["cells"][10].endswith("by admin")
    assert kept["links"]["episode-view"] == "/console/runs/run-b/viewer"  # the whole run
    assert kept["cells"][5:8] == ["whole run", "open in viewer", "-"] and kept["cells"][10] == ""
    assert page(browser, kept["links"]["episode-view"])  # it opens
    splits = re.search(r'<dd id="splits">(.*?)</dd>', text, re.S)
    assert splits and all(f'data-split="{s}"' in splits[1] for s in {e["split"] for e in api})


def test_episodes_come_a_page_at_a_time_by_the_apis_cursor(console: Depot, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(console_datasets, "PAGE", 3)
    alice = writer(console)
    for start in range(100, 1100, 100):
        alice.annotate("run-a", "frame", start, kind="tick")
    alice.create_dataset("ticks", event_window={"event": ["tick"]})
    browser = signed_in(console)
    path, seen, pages = "/console/datasets/ticks/1", [], 0
    api_cursor = None
    while True:
        text = page(browser, path)
        rows = episode_rows(text)
        api = alice.dataset_version("ticks", 1, limit=3, cursor=api_cursor)
        assert [r["index"] for r in rows] == [e["index"] for e in api["episodes_page"]]
        assert all(
            r["cells"][5:7] == [str(e["start"]), str(e["end"])] for r, e in zip(rows, api["episodes_page"], strict=True)
        )
        seen += [r["index"] for r in rows]
        pages += 1
        assert ('id="first-page"' in text) == (pages > 1)
        found = re.search(r'<a href="([^"]+)" id="next-page"', text)
        api_cursor = api["next_cursor"]
        if found is None:
            assert api_cursor is None
            break
        path = html.unescape(found[1])
        assert parse_qs(urlsplit(path).query) == {"cursor": [api_cursor]}
    assert seen == list(range(10)) and pages == 4

    alice.create_dataset("other", event_window={"event": ["tick"]})
    foreign = alice.dataset_version("other", 1, limit=3)["next_cursor"]
    for cursor in (foreign, "nonsense"):
        text = page(browser, f"/console/datasets/ticks/1?cursor={cursor}", 422)
        assert 'id="problem"' in text and "cursor" in text and 'id="ref">ticks@1</code>' in text
        assert episode_rows(text) == [] and 'href="/console/datasets/ticks/1" id="first-page"' in text


def test_unknown_names_and_versions_are_the_consoles_404_page(console: Depot) -> None:
    writer(console).create_dataset("there")
    browser = signed_in(console)
    for path, says in (
        ("/console/datasets/nope", "no dataset &#39;nope&#39;"),
        ("/console/datasets/nope/1", "no dataset &#39;nope&#39;"),
        ("/console/datasets/there/2", "has no version 2: it has there@1"),
        ("/console/datasets/there/0", "has no version &#39;0&#39;"),
        ("/console/datasets/there/x", "has no version &#39;x&#39;"),
        ("/console/datasets/there/1e3", "has no version"),
        (f"/console/datasets/there/{2**63}", "has no version"),
    ):
        text = page(browser, path, 404)
        assert "<h1>404 · NOT_FOUND</h1>" in text and says in text, (path, text[:2000])
    # What can be no id at all is refused by the depot's rule for every path (a 422 page), shown escaped.
    for path in ("/console/datasets/there/%C2%B2", "/console/datasets/%3Cscript%3Ealert(1)%3C%2Fscript%3E"):
        text = page(browser, path, 422)
        assert "<h1>422 · INVALID_ARGUMENT</h1>" in text and "is not an id of this depot" in text
        assert "<script>alert(1)" not in text and text.count("<script") == 2


def test_the_pages_need_a_login_that_reads(console: Depot) -> None:
    writer(console).create_dataset("there")
    anonymous = TestClient(console.app)
    for path in ("/console/datasets", "/console/datasets/there", "/console/datasets/there/1"):
        answer = anonymous.get(path, follow_redirects=False)
        assert answer.status_code == 303 and answer.headers["location"].startswith("/console/login?next=")
        assert page(signed_in(console, "read"), path)


# --- hostile text ----------------------------------------------------------------------------------------


def test_hostile_text_in_a_selection_or_a_skipped_run_is_shown_never_run(console: Depot) -> None:
    alice = writer(console)
    alice.create_dataset(
        "hostile", robot=[HOSTILE], tag=[HOSTILE], properties={"fleet.site": HOSTILE}, application=["<b>bold</b>"]
    )
    with session_scope(console.app.state.catalog, write=True) as session:  # a version skipping a run, with why
        skipped = json.dumps([{"run": HOSTILE, "why": HOSTILE}])
        facts = queries.VersionFacts("{}", HOSTILE, dt.datetime.now(dt.UTC), None, 0, skipped)
        queries.add_version(session, "hostile", facts, [])
    browser = signed_in(console)
    for path in (
        "/console/datasets",
        "/console/datasets/hostile",
        "/console/datasets/hostile/1",
        "/console/datasets/hostile/2",
    ):
        text = page(browser, path)
        assert "<script>alert" not in text and "<img src=x" not in text and "<b>bold" not in text, path
        assert text.count("<script") == 2  # the depot's own two (htmx and console.js)
    first = page(browser, "/console/datasets/hostile/1")
    shown = re.search(r'<pre id="selection">(.*?)</pre>', first, re.S)
    assert shown and json.loads(html.unescape(shown[1]))["tag"] == [HOSTILE]
    second = page(browser, "/console/datasets/hostile/2")
    why = re.search(r'<td class="why">(.*?)</td>', second, re.S)
    assert why and html.unescape(why[1]) == HOSTILE
    skipped_row = re.search(r'<table class="skipped">(.*?)</table>', second, re.S)
    assert skipped_row and "/console/runs/%3C%2Fpre%3E%3Cscript%3E" in skipped_row[1]
    assert 'id="created-by">&lt;/pre&gt;&lt;script&gt;' in second


def test_a_version_lists_its_exports_and_each_episode_s_quality_flags(console: Depot, tmp_path: Path):
    from services.datasets import exports
    from services.datasets.export import ExportSpec
    from services.datasets.quality import Limits
    from services.datasets.resolve import Sources

    alice = writer(console)
    alice.create_dataset("flags", timeline="log_time")
    staging = tmp_path / "allowed"
    places = exports.Places((staging.as_uri(),), tmp_path / "staging")
    request = exports.ExportRequest(
        "flags", 1, "lerobot", (staging / "x").as_uri(),
        ExportSpec(("/nowhere",), (), (), "t", 10), Limits(), strict=False,
    )  # fmt: skip
    state = console.app.state
    found = Sources(state.catalog, state.node.tiers.warm, state.ingest, state.node.clock)
    job = exports.create(found, places, request, "alice")
    assert exports.run_due(found, places, "node") == job["id"]
    text = signed_in(console).get("/console/datasets/flags/1").text
    assert f'data-export="{job["id"]}" data-state="failed"' in text  # no episode has /nowhere
    rows = {int(m.group(1)): m.group(5) for m in ROW.finditer(text)}
    assert rows and all("missing_entity /nowhere" in body for body in rows.values())
