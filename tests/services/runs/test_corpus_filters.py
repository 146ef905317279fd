"""Finding runs by what the corpus knows of them: metric conditions, tags, events, and sorting by
a metric with cursor pages, on DuckDB and Postgres alike (services/runs/corpus_filters.py)."""

from __future__ import annotations

import base64
import json
from typing import Any

import pytest
from sqlalchemy.orm import Session

from core.errors import BadParameterError
from services.runs import service
from services.runs.corpus_filters import MetricCondition
from services.runs.service import RunFilter
from tests.services.runs.corpus_scene import IDS, expected, write_scene


@pytest.fixture
def scene(session: Session) -> Session:
    write_scene(session)
    return session


def found(session: Session, **kwargs: Any) -> list[str]:
    runs, _ = service.list_runs(session, RunFilter(sort="id", **kwargs))
    return [r.id for r in runs]


FILTERS: list[dict[str, Any]] = [
    {"metric": ["distance_m>100"]},
    {"metric": ["distance_m>=100"]},
    {"metric": ["distance_m<100"]},
    {"metric": ["distance_m<=100"]},
    {"metric": ["distance_m=150"]},
    {"metric": ["distance_m!=150"]},
    {"metric": ["temp_c<0"]},
    {"metric": ["temp_c>-10"]},
    {"metric": ["sw_version=2.3"]},  # a text metric: its text
    {"metric": ["sw_version!=2.3"]},
    {"metric": ["distance_m>90", "distance_m<=150", "sw_version=2.3"]},
    {"tag": ["night-shift"]},
    {"tag": ["night-shift", "dock-2"]},  # both
    {"event": ["intervention"]},  # made by a rule or a person
    {"event": ["hard_brake"]},  # made by a robot
    {"event": ["intervention", "hard_brake"]},
    {"metric": ["distance_m>=100"], "tag": ["dock-2"], "event": ["intervention"]},
    {"tag": ["nobody-has-it"]},
    {"metric": ["no_such_metric>0"]},
]


@pytest.mark.parametrize("flt", FILTERS, ids=[json.dumps(f) for f in FILTERS])
def test_filters_keep_the_runs_the_scene_says(scene: Session, flt: dict[str, Any]):
    assert found(scene, **flt) == expected(flt)


def test_the_expected_answers_are_not_trivial():
    assert expected({"metric": ["distance_m>100"]}) == ["r-1", "r-4"]
    assert expected({"metric": ["sw_version=2.3"]}) == ["r-1", "r-3"]
    assert expected({"metric": ["distance_m!=150"]}) == ["r-2", "r-3"]  # r-5 and r-6 have no distance
    assert expected({"tag": ["night-shift", "dock-2"]}) == ["r-1"]
    assert expected({"event": ["intervention"]}) == ["r-1", "r-3", "r-5"]


def test_corpus_filters_combine_with_the_others(scene: Session):
    assert found(scene, metric=["distance_m>=100"], robot=["robot-b"]) == ["r-3", "r-4"]
    assert found(scene, tag=["night-shift"], status="closed", robot=["robot-a"]) == ["r-1", "r-2", "r-5"]


def pages(session: Session, sort: str, limit: int) -> list[list[str]]:
    out, cursor = [], None
    while True:
        runs, cursor = service.list_runs(session, RunFilter(sort=sort, limit=limit, cursor=cursor))
        out.append([r.id for r in runs])
        if cursor is None:
            return out


def test_sort_by_a_metric_puts_runs_without_it_last_either_way(scene: Session):
    # distance: r-2 80, r-3 100, r-1 150, r-4 150 (ties by id); r-5, r-6 have none
    assert found(scene) == IDS
    ascending, _ = service.list_runs(scene, RunFilter(sort="metric.distance_m"))
    assert [r.id for r in ascending] == ["r-2", "r-3", "r-1", "r-4", "r-5", "r-6"]
    descending, _ = service.list_runs(scene, RunFilter(sort="-metric.distance_m"))
    assert [r.id for r in descending] == ["r-4", "r-1", "r-3", "r-2", "r-6", "r-5"]


@pytest.mark.parametrize("limit", [1, 2, 4])
@pytest.mark.parametrize("sort", ["metric.distance_m", "-metric.distance_m", "-metric.temp_c", "metric.nothing"])
def test_cursor_pages_of_a_metric_sort_cover_every_run_once_in_order(scene: Session, sort: str, limit: int):
    whole, _ = service.list_runs(scene, RunFilter(sort=sort, limit=100))
    paged = pages(scene, sort, limit)
    assert [run for page in paged for run in page] == [r.id for r in whole]
    assert sorted(r.id for r in whole) == IDS
    assert all(len(page) <= limit for page in paged)


def test_a_metric_sort_pages_with_filters(scene: Session):
    first, cursor = service.list_runs(scene, RunFilter(sort="-metric.distance_m", tag=["dock-2"], limit=1))
    rest, end = service.list_runs(scene, RunFilter(sort="-metric.distance_m", tag=["dock-2"], limit=1, cursor=cursor))
    assert [r.id for r in first + rest] == ["r-4", "r-1"] and end is None


def _cursor(payload: object) -> str:
    return base64.urlsafe_b64encode(json.dumps(payload).encode()).decode().rstrip("=")


@pytest.mark.parametrize(
    ("kwargs", "name", "says"),
    [
        ({"metric": ["distance_m"]}, "metric", "NAME OP VALUE"),
        ({"metric": ["distance_m>"]}, "metric", "no value after '>'"),
        ({"metric": ["distance_m>far"]}, "metric", "compares numbers"),
        ({"metric": ["distance_m>nan"]}, "metric", "compares numbers"),
        ({"metric": [">100"]}, "metric", "NAME OP VALUE"),
        ({"metric": ["distance m>100"]}, "metric", "NAME OP VALUE"),
        ({"metric": ["distance_m=>100"]}, "metric", "two operators"),
        ({"metric": ["d\x00>1"]}, "metric", "NUL"),
        ({"metric": [f"m{i}>1" for i in range(33)]}, "metric", "at most 32"),
        ({"tag": ["x"] * 33}, "tag", "at most 32"),
        ({"event": ["e\x00"]}, "event", "NUL"),
        ({"sort": "metric."}, "sort", "metric.NAME"),
        ({"sort": "metric.a b"}, "sort", "metric.NAME"),
        ({"sort": "-metric.distance_m", "cursor": _cursor(["far", "r-1"])}, "cursor", "not a cursor"),
        ({"sort": "metric.distance_m", "cursor": _cursor([True, "r-1"])}, "cursor", "not a cursor"),
        ({"sort": "metric.distance_m", "cursor": _cursor(["2026-11-01T08:00:00+00:00", "r-1"])}, "cursor", "cursor"),
    ],
)
def test_bad_corpus_filters_are_422_naming_the_problem(scene: Session, kwargs: dict[str, Any], name: str, says: str):
    with pytest.raises(BadParameterError) as info:
        service.list_runs(scene, RunFilter(**kwargs))
    assert info.value.parameter == name and says in str(info.value)
    assert info.value.http_status() == 422


def test_a_metric_condition_says_its_form():
    with pytest.raises(BadParameterError, match=r"> >= < <= = !="):
        MetricCondition.parse("distance_m~100")
    assert MetricCondition.parse(" distance_m >= 1e2 ") == MetricCondition("distance_m", ">=", "1e2", 100.0)
    assert MetricCondition.parse("sw_version=2.3-rc1").number is None
