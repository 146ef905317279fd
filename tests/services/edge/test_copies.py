"""Robot copies: the latest report of what a robot holds of a run, replaced by the next, removed
when the robot deletes its copy; shown on the run's page with its latest pulls."""

from __future__ import annotations

import datetime as dt

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog.edge import RUN_PAGE_PULLS, PullAsk
from core.errors import BadParameterError, NotFoundError, PermissionDeniedError
from services.edge.context import Edge
from services.edge.copies import CopyFigures, forget_copy, report_copy
from services.edge.pulls import request_pull
from services.runs.service import run_answer
from tests.services.edge.conftest import ADMIN, OTHER_ROBOT, ROBOT, add_run, refused, robot_token
from tests.services.retention.conftest import Clock

RUN = "copied-run"
KEEPS_UNTIL = dt.datetime(2026, 11, 25, 8, 0, tzinfo=dt.UTC)
FIGURES = CopyFigures(
    chunks=120,
    bytes=1_500_000,
    local_only_chunks=20,
    local_only_bytes=900_000,
    local_only_entities=["/camera/front", "/lidar"],
    keeps_until=KEEPS_UNTIL,
)


@pytest.fixture
def run(catalog: sessionmaker[Session]) -> str:
    add_run(catalog, RUN, robot=ROBOT)
    return RUN


def test_a_robot_reports_its_copy(edge: Edge, run: str, clock: Clock, catalog: sessionmaker[Session]):
    copy = report_copy(edge, robot_token(), RUN, FIGURES)["robot_copy"]
    assert copy == {
        "run_id": RUN,
        "robot_id": ROBOT,
        "reported_at": clock.now.isoformat().replace("+00:00", "Z"),
        "chunks": 120,
        "bytes": 1_500_000,
        "local_only_chunks": 20,
        "local_only_bytes": 900_000,
        "local_only_entities": ["/camera/front", "/lidar"],
        "keeps_until": "2026-11-25T08:00:00Z",
    }
    assert run_answer(catalog, RUN, None)["robot_copy"] == copy
    clock.advance(minutes=5)
    later = CopyFigures(chunks=140, bytes=1_700_000, keeps_until=dt.datetime(2026, 11, 26, 8, 0))  # no zone: UTC
    replaced = report_copy(edge, ADMIN, RUN, later)["robot_copy"]
    assert (replaced["chunks"], replaced["local_only_chunks"], replaced["local_only_entities"]) == (140, 0, [])
    assert replaced["keeps_until"] == "2026-11-26T08:00:00Z" and replaced["reported_at"] != copy["reported_at"]
    assert run_answer(catalog, RUN, None)["robot_copy"] == replaced


def test_a_robot_deletes_its_copy(edge: Edge, run: str, catalog: sessionmaker[Session]):
    report_copy(edge, robot_token(), RUN, FIGURES)
    assert forget_copy(edge, robot_token(), RUN) == {"run": RUN, "removed": True, "robot_copy": None}
    assert run_answer(catalog, RUN, None)["robot_copy"] is None
    assert forget_copy(edge, ADMIN, RUN) == {"run": RUN, "removed": False, "robot_copy": None}  # again: nothing


def test_a_run_the_catalog_lacks_yet_is_404_retry_later(edge: Edge):
    for call in (
        lambda: report_copy(edge, robot_token(), "not-yet", FIGURES),
        lambda: forget_copy(edge, ADMIN, "not-yet"),
    ):
        with refused(NotFoundError, 404, "no run 'not-yet' in the catalog yet", "retry later"):
            call()


def test_a_robot_reports_its_own_runs_only(edge: Edge, run: str):
    for call in (
        lambda: report_copy(edge, robot_token(OTHER_ROBOT), RUN, FIGURES),
        lambda: forget_copy(edge, robot_token(OTHER_ROBOT), RUN),
    ):
        with refused(PermissionDeniedError, 403, f"belongs to robot '{ROBOT}'", f"robot '{OTHER_ROBOT}' only"):
            call()


@pytest.mark.parametrize(
    ("figures", "name", "says"),
    [
        (CopyFigures(chunks=-1, bytes=0), "chunks", "-1 is negative"),
        (CopyFigures(chunks=5, bytes=10, local_only_chunks=6), "local_only_chunks", "6 is more than the copy's 5"),
        (CopyFigures(chunks=5, bytes=10, local_only_bytes=11), "local_only_bytes", "11 is more than the copy's 10"),
        (CopyFigures(chunks=5, bytes=10, local_only_entities=["lidar"]), "local_only_entities", "'lidar' is not"),
        (CopyFigures(chunks=5, bytes=10, local_only_entities=["/a\x00"]), "local_only_entities", "no NUL"),
        (CopyFigures(chunks=5, bytes=10, local_only_entities=["/a"] * 10_001), "local_only_entities", "at most 10000"),
    ],
)
def test_figures_that_are_not_are_refused_by_name(edge: Edge, run: str, figures: CopyFigures, name: str, says: str):
    with refused(BadParameterError, 422, f"parameter '{name}'", says):
        report_copy(edge, robot_token(), RUN, figures)


def test_a_runs_page_shows_its_latest_pulls(edge: Edge, run: str, catalog: sessionmaker[Session], clock: Clock):
    assert run_answer(catalog, RUN, None)["pulls"] == []
    made = []
    for i in range(RUN_PAGE_PULLS + 2):
        made.append(request_pull(edge, PullAsk(RUN, [f"/e{i}"], [], None, None, None), "alice")[0]["pull"])
        clock.advance(seconds=1)
    page = run_answer(catalog, RUN, None)
    assert page["pulls"] == made[::-1][:RUN_PAGE_PULLS]
    assert page["id"] == RUN and page["robot_copy"] is None  # the rest of the page as before
