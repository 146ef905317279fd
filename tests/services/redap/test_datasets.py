"""Dataset and segment lookups in the catalog (services/redap/datasets.py), on DuckDB and Postgres:
a dataset by its entry id, a segment of it, and the segment table's rows read a page at a time."""

from __future__ import annotations

import datetime as dt
from typing import Any

import pytest
from sqlalchemy.orm import Session

from catalog import queries
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from core.errors import NotFoundError
from services.redap import datasets
from services.redap.tuid import Tuid
from tests.services.redap import depots

NOW = dt.datetime(2026, 11, 21, 12, 0, tzinfo=dt.UTC)


def record(run_id: str, application: str = "nav", **changes: Any) -> RunRecord:
    """A sealed run's record (tests change its tier where they need another)."""
    return depots.record(run_id, application, **{"tier": "warm", **changes})


def save(session: Session, *records: RunRecord, tiers: dict[str, str] | None = None) -> None:
    for made in records:
        queries.save_run(session, made, NOW)
    for run_id, tier in (tiers or {}).items():  # retention moves runs on; their rows say where they are
        run = queries.get_run(session, run_id)
        assert run is not None
        if tier == "deleted":  # as retention deletes a run
            queries.mark_deleted(session, run_id, NOW)
        else:
            run.tier = tier
    session.flush()


def entry_of(session: Session, name: str) -> Tuid:
    found = queries.dataset_entry_id(session, name)
    assert found is not None
    return Tuid.parse(found)


def test_a_dataset_is_found_by_its_entry_id_and_an_unknown_id_says_how_to_list_them(session: Session):
    save(session, record("run-1"), record("run-2", "arm"))
    assert datasets.dataset_by_entry(session, entry_of(session, "arm")).name == "arm"
    with pytest.raises(NotFoundError, match=r"no dataset has entry id 18EA6CA8C3020B3029d1569232672548.*FindEntries"):
        datasets.dataset_by_entry(session, Tuid.parse("18EA6CA8C3020B3029d1569232672548"))


def test_a_segment_is_one_of_the_datasets_runs(session: Session):
    save(session, record("run-1"), record("run-2", "arm"))
    nav = datasets.dataset_by_entry(session, entry_of(session, "nav"))
    assert datasets.segment_run(session, nav, "run-1").id == "run-1"
    for other in ("run-2", "no-such-run"):  # another dataset's run, or none at all
        with pytest.raises(NotFoundError, match=f"dataset 'nav' has no segment '{other}'"):
            datasets.segment_run(session, nav, other)


def test_segments_are_the_runs_of_every_tier_but_deleted(session: Session):
    runs = [record(f"run-{tier}") for tier in ("hot", "warm", "cold", "deleted")]
    save(
        session, *runs, record("run-arm", "arm"), tiers={"run-cold": "cold", "run-deleted": "deleted", "run-hot": "hot"}
    )
    nav = datasets.dataset_by_entry(session, entry_of(session, "nav"))
    assert [r.id for r in datasets.dataset_runs(session, nav)] == ["run-cold", "run-hot", "run-warm"]
    rows = datasets.segment_rows(session, "nav", None, 10)
    assert [(r.run_id, r.tier) for r in rows] == [("run-cold", "cold"), ("run-hot", "hot"), ("run-warm", "warm")]


def test_segment_rows_come_in_pages_in_id_order_with_their_timelines(session: Session):
    save(session, *(record(f"run-{i}", timelines=[TimelineRecord("frame", "sequence", i, i + 5)]) for i in range(5)))
    first = datasets.segment_rows(session, "nav", None, 2)
    second = datasets.segment_rows(session, "nav", first[-1].run_id, 2)
    third = datasets.segment_rows(session, "nav", second[-1].run_id, 2)
    assert [[r.run_id for r in page] for page in (first, second, third)] == [
        ["run-0", "run-1"],
        ["run-2", "run-3"],
        ["run-4"],
    ]
    assert datasets.segment_rows(session, "nav", "run-4", 2) == []
    assert third[0].timelines == {"frame": ("sequence", 4, 9)}


def test_segment_rows_hold_what_the_table_shows(session: Session):
    save(session, record("run-1", properties={"fleet": {"robot_id": "robot-7"}, "recording": {"x": 1}}))
    queries.require_run(session, "run-1").pinned = True
    session.flush()
    (row,) = datasets.segment_rows(session, "nav", None, 10)
    assert (row.run_id, row.robot_id, row.status, row.tier, row.pinned) == ("run-1", "robot-7", "closed", "warm", True)
    assert (row.chunks, row.bytes) == (3, 1000)
    assert (row.started_at, row.ended_at, row.updated_at) == (NOW - dt.timedelta(minutes=5), NOW, NOW)
    assert row.properties == {"fleet": {"robot_id": "robot-7"}, "recording": {"x": 1}}
    assert row.timelines == {"frame": ("sequence", 0, 9)}


def test_named_segments_are_only_the_datasets_own(session: Session):
    save(session, record("run-1"), record("run-2"), record("run-3", "arm"), record("run-4"), tiers={"run-4": "deleted"})
    named = datasets.segment_rows_named(session, "nav", ["run-2", "run-3", "run-4", "nope", "run-1"])
    assert [r.run_id for r in named] == ["run-1", "run-2"]
    assert datasets.segment_rows_named(session, "nav", []) == []


def test_property_pages_read_every_runs_properties(session: Session):
    save(session, *(record(f"run-{i}", properties={"fleet": {"n": i}}) for i in range(5)), record("run-x", "arm"))
    pages = list(datasets.property_pages(session, "nav", 2))
    assert [len(page) for page in pages] == [2, 2, 1]
    assert [p["fleet"]["n"] for page in pages for p in page] == [0, 1, 2, 3, 4]


def test_a_timeline_has_the_type_most_runs_log_it_with(session: Session):
    save(
        session,
        record(
            "run-1", timelines=[TimelineRecord("t", "sequence", 0, 1), TimelineRecord("log_time", "timestamp", 1, 2)]
        ),
        record("run-2", timelines=[TimelineRecord("t", "duration", 0, 1)]),
        record("run-3", timelines=[TimelineRecord("t", "duration", 0, 1)]),
        record("run-4", "arm", timelines=[TimelineRecord("arm_only", "sequence", 0, 1)]),
    )
    assert datasets.timeline_types(session, "nav") == {"t": "duration", "log_time": "timestamp"}


def test_property_archetypes_are_those_of_property_entities_only(session: Session):
    entities = [
        EntityRecord("/__properties", 1, 1, 1, 10, ["rerun.archetypes.RecordingInfo"], ["RecordingInfo:start_time"]),
        EntityRecord("/__properties/location", 1, 1, 1, 10, ["rerun.archetypes.GeoPoints"], ["GeoPoints:positions"]),
        EntityRecord(
            "/x_properties", 1, 1, 1, 10, ["rerun.archetypes.TextLog"], ["TextLog:text"]
        ),  # `_` is no wildcard
        EntityRecord("/world", 1, 0, 1, 10, ["rerun.archetypes.Points3D"], ["Points3D:positions"]),
    ]
    save(session, record("run-1", entities=entities), record("run-2", "arm", entities=entities[3:]))
    assert datasets.property_archetypes(session, "nav") == {
        "/__properties": {"rerun.archetypes.RecordingInfo"},
        "/__properties/location": {"rerun.archetypes.GeoPoints"},
    }
    assert datasets.property_archetypes(session, "arm") == {}


def test_a_page_holds_its_own_runs_timelines_only(session: Session):
    save(
        session,
        record("run-1", timelines=[TimelineRecord("frame", "sequence", 1, 2)]),
        record("run-2", "arm", timelines=[TimelineRecord("arm_time", "sequence", 0, 1)]),  # between nav's runs
        record("run-3", timelines=[TimelineRecord("frame", "sequence", 3, 4)]),
    )
    found = {r.run_id: r.timelines for r in datasets.segment_rows(session, "nav", None, 10)}
    assert found == {"run-1": {"frame": ("sequence", 1, 2)}, "run-3": {"frame": ("sequence", 3, 4)}}
    named = datasets.segment_rows_named(session, "nav", ["run-3", "run-1"])
    assert [r.timelines for r in named] == [{"frame": ("sequence", 1, 2)}, {"frame": ("sequence", 3, 4)}]
