"""Dataset snapshots over REST with auth on, through the REST client: versions written one after
the other and never changed, listed, shown a page of episodes at a time; bad selections and
unknown names answered plainly."""

from __future__ import annotations

import datetime as dt

import pytest

from catalog import corpus
from catalog.db import session_scope
from tests.services.auth.conftest import Depot, bearer
from tests.services.corpus.conftest import catalog_of, refused, sdk
from tests.services.datasets.conftest import upload, writer


def test_a_new_create_is_the_next_version_and_older_ones_stay_as_they_were(depot: Depot):
    upload(depot, "run-a")
    alice = writer(depot)
    one = alice.create_dataset("picks", robot=["robot-7"], fps=10, split={"train": 0.5, "val": 0.5}, seed=3)
    assert (one["name"], one["version"], one["ref"], one["created_by"]) == ("picks", 1, "picks@1", "alice")
    assert one["rules_version"] is None and one["created_at"].endswith("Z")
    assert sum(s["episodes"] for s in one["splits"].values()) == 1
    before = alice.dataset_version("picks", 1, chunk_ids=True)

    upload(depot, "run-b")
    with session_scope(catalog_of(depot), write=True) as session:  # the rules running now: version 1
        corpus.add_rules_version(session, "", "bob", dt.datetime.now(dt.UTC))
    two = alice.create_dataset("picks", robot=["robot-7"], fps=10, split={"train": 0.5, "val": 0.5}, seed=3)
    assert (two["version"], two["ref"], two["episodes"], two["rules_version"]) == (2, "picks@2", 2, 1)
    assert alice.dataset_version("picks", 1, chunk_ids=True) == before  # immutable
    assert [v["version"] for v in alice.dataset("picks")["versions"]] == [2, 1]
    listed = sdk(depot, depot.token("read")).datasets()
    assert [(d["name"], d["latest"]["ref"]) for d in listed] == [("picks", "picks@2")]

    shown = alice.dataset_version("picks", 2)
    assert shown["selection"]["robot"] == ["robot-7"] and shown["selection"]["fps"] == 10
    assert shown["selection"]["split"] == {"train": 0.5, "val": 0.5} and shown["selection"]["seed"] == 3
    episode = shown["episodes_page"][0]
    assert set(episode) == {
        "index", "run_id", "robot_id", "split", "timeline", "start", "end", "event_id", "chunks", "bytes",
        "missing", "missing_why",
    }  # fmt: skip
    assert episode["split"] in ("train", "val") and "chunk_ids" not in episode


def test_every_episode_of_a_run_is_in_its_split(depot: Depot):
    upload(depot, "run-a")
    upload(depot, "run-b")
    alice = writer(depot)
    for start in (200, 500, 800):
        alice.annotate("run-a", "frame", start, kind="grasp")
        alice.annotate("run-b", "frame", start, kind="grasp")
    made = alice.create_dataset(
        "split", event_window={"event": ["grasp"], "before_s": 10}, split={"train": 0.5, "val": 0.5}, seed=11
    )
    episodes = alice.dataset_version("split", 1)["episodes_page"]
    by_run: dict[str, set[str]] = {}
    for e in episodes:
        by_run.setdefault(e["run_id"], set()).add(e["split"])
    assert made["episodes"] == 6 and all(len(splits) == 1 for splits in by_run.values())
    again = alice.create_dataset(
        "split", event_window={"event": ["grasp"], "before_s": 10}, split={"train": 0.5, "val": 0.5}, seed=11
    )
    assert again["splits"] == made["splits"]  # the same seed: the same split


def test_episodes_come_a_page_at_a_time(depot: Depot):
    upload(depot, "run-a")
    alice = writer(depot)
    for start in range(100, 1100, 100):
        alice.annotate("run-a", "frame", start, kind="tick")
    alice.create_dataset("ticks", event_window={"event": ["tick"]})
    seen, cursor = [], None
    while True:
        page = alice.dataset_version("ticks", 1, limit=3, cursor=cursor)
        seen += [e["index"] for e in page["episodes_page"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == list(range(10))
    alice.create_dataset("other", event_window={"event": ["tick"]})
    first = alice.dataset_version("ticks", 1, limit=3)["next_cursor"]
    refused(lambda: alice.dataset_version("ticks", 1, cursor="nonsense"), 422, "cursor")
    refused(lambda: alice.dataset_version("other", 1, limit=3, cursor=first), 422, "cursor", "this version")
    refused(lambda: alice.dataset_version("ticks", 1, limit=0), 422, "limit")


def test_unknown_names_and_versions_are_404_with_a_hint(depot: Depot):
    reader = sdk(depot, depot.token("read"))
    refused(lambda: reader.dataset("nope"), 404, "no dataset 'nope'", "fleet datasets ls")
    refused(lambda: reader.dataset_version("nope", 1), 404, "no dataset 'nope'")
    writer(depot).create_dataset("there")
    refused(lambda: reader.dataset_version("there", 2), 404, "no version 2", "there@1")
    answer = depot.client.get("/v1/datasets/there/0", headers=bearer(depot.token("read")))
    assert answer.status_code == 422 and "version" in answer.json()["message"]


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"name": "-bad"}, "'name'"),
        ({"name": "ok", "split": {"train": 0.9, "val": 0.2}}, "'split'"),
        ({"name": "ok", "fps": -1}, "'fps'"),
        ({"name": "ok", "event_window": {"event": ["x"], "before_s": -5}}, "'event_window.before_s'"),
        ({"name": "ok", "event_window": {"event": ["x"], "before_s": 3600, "after_s": 1}}, "'event_window'"),
        ({"name": "ok", "since": "yesterday"}, "'since'"),
        ({"name": "ok", "include": ["nope"]}, "'include'"),
        ({"name": "ok", "status": "asleep"}, "'status'"),
        ({"name": "ok", "seed": "one"}, "'seed'"),
        ({"name": "ok", "colour": "red"}, "'colour'"),
    ],
)
def test_a_bad_selection_is_one_422_naming_the_field(depot: Depot, body: dict[str, object], field: str):
    answer = depot.client.post("/v1/datasets", json=body, headers=bearer(depot.token("write")))
    assert answer.status_code == 422, answer.text
    assert field in answer.json()["message"], answer.json()
    assert writer(depot).datasets() == []  # nothing written


def test_reading_needs_read_and_making_needs_write(depot: Depot):
    refused(lambda: sdk(depot, depot.token("read")).create_dataset("x"), 403, "'write'")
    refused(lambda: sdk(depot, depot.token("ingest", robot="robot-7")).datasets(), 403, "'read'")
