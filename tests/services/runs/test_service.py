"""Finding runs: filters, sort and cursor pages, on DuckDB and Postgres alike."""

from __future__ import annotations

import base64
import datetime as dt
import json

import pytest
from sqlalchemy.orm import Session

from catalog import queries
from catalog.queries import EntityRecord
from core.errors import BadParameterError, NotFoundError
from services.runs import service
from services.runs.service import RunFilter, parse_properties, parse_time
from tests.catalog.records import run_record

T0 = dt.datetime(2026, 11, 1, 8, 0, tzinfo=dt.UTC)


def _add(
    session: Session,
    run_id: str,
    robot: str,
    app: str,
    hours: int,
    *,
    status: str = "closed",
    entities: tuple[str, ...] = ("/world/points",),
    size: int = 100,
) -> None:
    start = T0 + dt.timedelta(hours=hours)
    queries.save_run(
        session,
        run_record(
            run_id,
            start,
            robot_id=robot,
            application_id=app,
            status=status,
            ended_at=None,
            bytes=size,
            properties={"fleet": {"robot_id": robot, "site": "lab" if hours % 2 else "field"}},
            entities=[EntityRecord(p, 1, 0, 1, 10, [], []) for p in entities],
        ),
        T0,
    )


@pytest.fixture
def fleet(session: Session) -> Session:
    _add(session, "r-a1", "robot-a", "nav", 0, entities=("/world/points", "/world/robot/lidar"), size=300)
    _add(session, "r-a2", "robot-a", "nav", 5, status="live", entities=("/robot/speed",), size=50)
    _add(session, "r-b1", "robot-b", "arm", 10, entities=("/world",), size=200)
    _add(session, "r-b2", "robot-b", "nav", 30, entities=("/worldwide/x",), size=10)
    session.flush()
    return session


def ids(session: Session, **kwargs: object) -> list[str]:
    runs, _ = service.list_runs(session, RunFilter(**kwargs))  # type: ignore[arg-type]
    return [r.id for r in runs]


def test_default_sort_is_newest_first(fleet: Session):
    assert ids(fleet) == ["r-b2", "r-b1", "r-a2", "r-a1"]
    assert ids(fleet, sort="started_at") == ["r-a1", "r-a2", "r-b1", "r-b2"]
    assert ids(fleet, sort="-bytes") == ["r-a1", "r-b1", "r-a2", "r-b2"]


def test_filters(fleet: Session):
    assert ids(fleet, robot=["robot-a"]) == ["r-a2", "r-a1"]
    assert ids(fleet, application=["nav"], robot=["robot-b"]) == ["r-b2"]
    assert ids(fleet, since=T0 + dt.timedelta(hours=5), until=T0 + dt.timedelta(hours=11)) == ["r-b1", "r-a2"]
    assert ids(fleet, status="live") == ["r-a2"]
    assert ids(fleet, entity=["/world/**"]) == ["r-b1", "r-a1"]  # the subtree, not /worldwide
    assert ids(fleet, entity=["/world/points"]) == ["r-a1"]
    assert ids(fleet, entity=["/world/**", "/world/robot/lidar"]) == ["r-a1"]
    assert ids(fleet, properties={"fleet.site": "lab"}) == ["r-a2"]  # hours 5 -> odd
    assert ids(fleet, properties={"fleet.robot_id": "robot-b", "fleet.site": "field"}) == ["r-b2", "r-b1"]


def test_cursor_pages_cover_everything_once(fleet: Session):
    seen, cursor = [], None
    while True:
        page, cursor = service.list_runs(fleet, RunFilter(limit=1, cursor=cursor, sort="-started_at"))
        seen += [r.id for r in page]
        if cursor is None:
            break
    assert seen == ["r-b2", "r-b1", "r-a2", "r-a1"]
    first, cursor = service.list_runs(fleet, RunFilter(limit=3, sort="id"))
    rest, end = service.list_runs(fleet, RunFilter(limit=3, sort="id", cursor=cursor))
    assert [r.id for r in first + rest] == ["r-a1", "r-a2", "r-b1", "r-b2"] and end is None


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"sort": "size"}, "sort"),
        ({"limit": 0}, "limit"),
        ({"limit": 1001}, "limit"),
        ({"status": "open"}, "status"),
        ({"tier": "lukewarm"}, "tier"),
        ({"cursor": "not-a-cursor"}, "cursor"),
        ({"properties": {"robot": "x"}}, "property"),
    ],
)
def test_bad_parameters_name_themselves(fleet: Session, kwargs: dict[str, object], name: str):
    with pytest.raises(BadParameterError) as info:
        service.list_runs(fleet, RunFilter(**kwargs))  # type: ignore[arg-type]
    assert info.value.parameter == name and f"parameter {name!r}" in str(info.value)
    assert info.value.http_status() == 422


def test_parsers():
    assert parse_time("since", "2026-11-21") == dt.datetime(2026, 11, 21, tzinfo=dt.UTC)
    assert parse_time("since", "2026-11-21T08:00:00Z") == dt.datetime(2026, 11, 21, 8, tzinfo=dt.UTC)
    with pytest.raises(BadParameterError, match="ISO-8601"):
        parse_time("until", "yesterday")
    assert parse_properties(["fleet.robot_id=r=1"]) == {"fleet.robot_id": "r=1"}
    with pytest.raises(BadParameterError, match=r"NAME\.FIELD=VALUE"):
        parse_properties(["fleet.robot_id"])


def test_get_run_and_robots(fleet: Session):
    assert queries.require_run(fleet, "r-a1").robot_id == "robot-a"
    with pytest.raises(NotFoundError, match="no run 'nope'") as info:
        queries.require_run(fleet, "nope")
    assert info.value.http_status() == 404
    assert [(robot.id, count) for robot, count in service.list_robots(fleet)] == [("robot-a", 2), ("robot-b", 2)]


def _cursor(payload: object) -> str:
    return base64.urlsafe_b64encode(json.dumps(payload).encode()).decode().rstrip("=")


@pytest.mark.parametrize(
    ("sort", "payload"),
    [
        ("-started_at", [{}, 1]),
        ("id", [{}, 1]),
        ("-bytes", [{}, 1]),
        ("-started_at", ["r-a1"]),
        ("-started_at", {"a": 1}),
        ("-started_at", 7),
        ("-started_at", [12, "r-a1"]),
        ("-started_at", ["not a date", "r-a1"]),
        ("started_at", [None, "r-a1"]),
        ("-bytes", ["300", "r-a1"]),
        ("bytes", [2**70, "r-a1"]),
        ("-bytes", [True, "r-a1"]),
        ("bytes", [1.5, "r-a1"]),
        ("id", [["r-a1"], "r-a1"]),
        ("id", ["r-a1", 5]),
        ("id", ["r-\u0000", "r-a1"]),
        ("-started_at", ["2026-11-01T08:00:00+00:00", "r-\u0000"]),
    ],
)
def test_tampered_cursor_is_a_bad_parameter(fleet: Session, sort: str, payload: object):
    """Valid base64 JSON of the wrong shape or types is refused before any query runs."""
    with pytest.raises(BadParameterError) as info:
        service.list_runs(fleet, RunFilter(sort=sort, cursor=_cursor(payload)))
    assert info.value.parameter == "cursor" and info.value.http_status() == 422


def test_oversized_and_deep_cursors_are_bad_parameters(fleet: Session):
    for cursor in ("A" * 5000, _cursor([[[[[]]]]] * 10), base64.urlsafe_b64encode(b"[" * 1500).decode()):
        with pytest.raises(BadParameterError) as info:
            service.list_runs(fleet, RunFilter(cursor=cursor))
        assert info.value.parameter == "cursor"


def test_property_filters_take_any_key(fleet: Session):
    """Quotes, slashes and tildes in a property name or field are matched as written, not parsed."""
    assert ids(fleet, properties={'fle"et.robot_id': "robot-a"}) == []
    assert ids(fleet, properties={'fleet.robot"_id': "robot-a"}) == []
    assert ids(fleet, properties={"fl/e~et.si/te~1": "lab"}) == []
    assert ids(fleet, properties={"fleet.site": "lab"}) == ["r-a2"]


def test_filter_counts_are_bounded(fleet: Session):
    many_entities = [f"/world/e{i}" for i in range(service.MAX_ENTITY_FILTERS + 1)]
    many_props = {f"fleet.f{i}": "x" for i in range(service.MAX_PROPERTY_FILTERS + 1)}
    for kwargs, name in (
        ({"entity": many_entities}, "entity"),
        ({"entity": many_entities * 40}, "entity"),
        ({"properties": many_props}, "property"),
        ({"robot": ["a\u0000"]}, "robot"),
        ({"properties": {"fleet.site": "l\u0000"}}, "property"),
    ):
        with pytest.raises(BadParameterError) as info:
            service.list_runs(fleet, RunFilter(**kwargs))  # type: ignore[arg-type]
        assert info.value.parameter == name and info.value.http_status() == 422
    # at the bound the query still runs and means what it says
    assert ids(fleet, entity=["/world/**"] * service.MAX_ENTITY_FILTERS) == ["r-b1", "r-a1"]
    assert ids(fleet, properties={f"fleet.f{i}": "x" for i in range(service.MAX_PROPERTY_FILTERS)}) == []
