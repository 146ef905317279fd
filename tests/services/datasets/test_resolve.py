"""A selection resolved against runs hot on this node and sealed in the warm store: one episode per
run, or one per event with its window; the chunk ids of each compared to an answer worked out from
the recording's own chunks; runs that cannot be read skipped with why."""

from __future__ import annotations

from pathlib import Path

import pytest

from catalog.models import Event
from services.datasets import resolve
from services.datasets.selection import EventWindow, Selection
from tests.services.auth.conftest import Depot
from tests.services.corpus.conftest import add_run, refused
from tests.services.datasets.conftest import expected_chunks, upload, writer


def _episodes(depot: Depot, name: str, version: int) -> list[dict[str, object]]:
    page = writer(depot).dataset_version(name, version, limit=1000, chunk_ids=True)
    assert page["next_cursor"] is None
    episodes: list[dict[str, object]] = page["episodes_page"]
    return episodes


def test_one_episode_per_run_reads_the_chunks_of_its_entities(depot: Depot, tmp_path: Path):
    hot = upload(depot, "run-hot")
    sealed = upload(depot, "run-sealed", chunks=9, seal=True)
    made = writer(depot).create_dataset("whole", include=["/robot/**"])
    assert (made["ref"], made["episodes"], made["runs"], made["skipped"]) == ("whole@1", 2, 2, [])
    episodes = _episodes(depot, "whole", 1)
    assert [e["run_id"] for e in episodes] == ["run-hot", "run-sealed"]  # in run id order
    for episode, data in zip(episodes, (hot, sealed), strict=True):
        assert (episode["start"], episode["end"], episode["event_id"], episode["timeline"]) == (
            None,
            None,
            None,
            "log_time",
        )
        assert episode["chunk_ids"] == expected_chunks(data, tmp_path, ["/robot/**"])
        assert episode["chunks"] == len(episode["chunk_ids"]) > 0  # type: ignore[arg-type]
        assert episode["missing"] is False
    assert made["chunks"] == sum(e["chunks"] for e in episodes)  # type: ignore[misc]
    assert made["bytes"] == sum(e["bytes"] for e in episodes) > 0  # type: ignore[misc]
    everything = writer(depot).create_dataset("all", exclude=["/arm/**"])
    (first, _) = _episodes(depot, "all", 1)
    assert everything["episodes"] == 2
    assert first["chunk_ids"] == expected_chunks(hot, tmp_path, ["/**"], exclude=("/arm/**",))


@pytest.mark.parametrize("seal", [False, True], ids=["hot", "sealed"])
def test_a_window_per_event_reads_its_chunks_and_the_scene_before_it(depot: Depot, tmp_path: Path, seal: bool):
    data = upload(depot, "run-a", seal=seal)
    upload(depot, "run-quiet")  # no event of the kind: no episode
    alice = writer(depot)
    late = alice.annotate("run-a", "frame", 600, end=606, kind="intervention")
    early = alice.annotate("run-a", "frame", 300, kind="intervention")
    alice.annotate("run-a", "frame", 900, kind="bump")  # another kind: no window
    made = alice.create_dataset(
        "windows",
        include=["/robot/**"],
        event_window={"event": ["intervention"], "before_s": 50, "after_s": 20},
    )
    assert (made["episodes"], made["runs"]) == (2, 1)
    first, second = _episodes(depot, "windows", 1)
    assert (first["event_id"], first["timeline"], first["start"], first["end"]) == (early["id"], "frame", 250, 320)
    assert (second["event_id"], second["start"], second["end"]) == (late["id"], 550, 626)
    assert first["chunk_ids"] == expected_chunks(data, tmp_path, ["/robot/**"], (250, 320))
    assert second["chunk_ids"] == expected_chunks(data, tmp_path, ["/robot/**"], (550, 626))
    assert second["chunk_ids"] != expected_chunks(data, tmp_path, ["/robot/**"])  # not the whole run


def test_a_fraction_of_a_step_on_a_sequence_timeline_is_a_whole_step(depot: Depot):
    upload(depot, "run-a")
    writer(depot).annotate("run-a", "frame", 600, kind="intervention")
    writer(depot).create_dataset("steps", event_window={"event": ["intervention"], "before_s": 0.5, "after_s": 1.2})
    (episode,) = _episodes(depot, "steps", 1)
    assert (episode["start"], episode["end"]) == (599, 602)


def test_a_window_on_a_timestamp_timeline_is_in_nanoseconds():
    selection = Selection(event_window=EventWindow(("x",), before_s=5, after_s=2.5))
    event = Event(id="ev-1", timeline="log_time", timeline_type="timestamp", range_start=10**18, range_end=10**18 + 7)
    window = resolve.event_window(selection, event)
    assert (window.timeline, window.start, window.end, window.latest_at) == (
        "log_time",
        10**18 - 5 * 10**9,
        10**18 + 7 + 2_500_000_000,
        True,
    )


def test_runs_that_cannot_be_read_are_skipped_with_why(depot: Depot):
    upload(depot, "run-a")
    add_run(depot, "run-elsewhere")  # a catalog row of a hot run this node does not hold
    made = writer(depot).create_dataset("mixed")
    assert made["episodes"] == 1 and made["runs"] == 1
    assert made["skipped"] == [
        {"run": "run-elsewhere", "why": "hot on another node: make the snapshot on its node, or once it is sealed"}
    ]
    shown = writer(depot).dataset_version("mixed", 1)
    assert shown["skipped"] == made["skipped"]


def test_more_runs_than_the_cap_is_refused(depot: Depot, monkeypatch: pytest.MonkeyPatch):
    for run_id in ("run-a", "run-b", "run-c"):
        add_run(depot, run_id)
    monkeypatch.setattr(resolve, "MAX_RUNS", 2)
    monkeypatch.setattr(resolve, "PAGE", 1)  # paged through, one run a page
    refused(lambda: writer(depot).create_dataset("big"), 422, "selection", "more than 2 runs", "narrow it")
    monkeypatch.setattr(resolve, "MAX_RUNS", 3)
    assert writer(depot).create_dataset("big", robot=["robot-7"])["skipped"] != []  # 3 runs: read (and skipped)


def test_the_run_filters_choose_the_runs(depot: Depot):
    upload(depot, "run-a", robot="robot-7")
    upload(depot, "run-b", robot="robot-9")
    writer(depot).tag("run-b", ["good"])
    made = writer(depot).create_dataset("filtered", robot=["robot-9"], tag=["good"])
    assert [e["run_id"] for e in _episodes(depot, "filtered", 1)] == ["run-b"] and made["runs"] == 1
    assert writer(depot).create_dataset("none", robot=["robot-1"])["episodes"] == 0
