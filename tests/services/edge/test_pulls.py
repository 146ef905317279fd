"""Pulls: queued for a run's robot, one per part asked while it is open, polled by the robot's
agent, moved through their states by its reports, cancelled; every refusal with its status."""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog.edge import PullAsk
from core.errors import BadParameterError, ConflictError, NotFoundError, PermissionDeniedError
from services.edge.context import Edge
from services.edge.pulls import (
    MAX_ERROR_CHARS,
    Progress,
    PullQuery,
    cancel_pull,
    pulls_answer,
    report_progress,
    request_pull,
    run_pulls_answer,
)
from tests.services.edge.conftest import ADMIN, OTHER_ROBOT, READER, ROBOT, WRITER, add_run, refused, robot_token
from tests.services.retention.conftest import Clock

RUN = "pulled-run"


@pytest.fixture
def run(catalog: sessionmaker[Session]) -> str:
    add_run(catalog, RUN, robot=ROBOT)
    return RUN


def pull(edge: Edge, run_id: str = RUN, by: str = "alice", **part: Any) -> dict[str, Any]:
    answer, created = request_pull(edge, PullAsk(run_id, **{**EVERYTHING, **part}), by)
    assert created
    made: dict[str, Any] = answer["pull"]
    return made


EVERYTHING: dict[str, Any] = {"include": [], "exclude": [], "timeline": None, "start": None, "end": None}


def progress(edge: Edge, pull_id: str, state: str, chunks: int = 0, sent: int = 0, *, principal=None, error=None):
    return report_progress(edge, principal or robot_token(), pull_id, Progress(state, chunks, sent, error))["pull"]


# --- asking -----------------------------------------------------------------------------------------


def test_a_pull_is_queued_for_the_runs_robot(edge: Edge, run: str, clock: Clock):
    part: dict[str, Any] = {
        "include": ["/world/**"],
        "exclude": ["/world/camera"],
        "timeline": "frame",
        "start": "10",
        "end": "20",
    }
    made = pull(edge, **part)
    assert re.fullmatch(r"pull-[0-9a-f]{12}", str(made["id"]))
    assert made == {
        "id": made["id"],
        "run_id": RUN,
        "robot_id": ROBOT,
        **part,
        "state": "pending",
        "requested_by": "alice",
        "requested_at": made["requested_at"],
        "updated_at": made["requested_at"],
        "chunks_sent": 0,
        "bytes_sent": 0,
        "error": None,
        "origin": "person",
        "event_id": None,
        "priority": None,
    }
    assert str(made["requested_at"]).startswith(clock.now.strftime("%Y-%m-%dT%H:%M"))


def test_asking_again_for_an_open_pull_answers_it_not_a_twin(edge: Edge, run: str):
    first = pull(edge, include=["/world/**"])
    answer, created = request_pull(edge, PullAsk(RUN, ["/world/**"], [], None, None, None), "bob")
    assert not created and answer["pull"] == first  # pending: the same pull, asked by whoever first did
    progress(edge, str(first["id"]), "sending", 3, 300)
    answer, created = request_pull(edge, PullAsk(RUN, ["/world/**"], [], None, None, None), "bob")
    assert not created and answer["pull"]["id"] == first["id"] and answer["pull"]["state"] == "sending"
    other = pull(edge, include=["/world/**"], exclude=["/world/camera"])  # another part: another pull
    assert other["id"] != first["id"]
    progress(edge, str(first["id"]), "done", 5, 500)
    again = pull(edge, include=["/world/**"])  # done: asking again queues a new one
    assert again["id"] not in (first["id"], other["id"])


def test_a_pull_of_a_run_the_catalog_lacks_is_404(edge: Edge):
    with refused(NotFoundError, 404, "no run 'nowhere'"):
        request_pull(edge, PullAsk("nowhere", [], [], None, None, None), "alice")
    with refused(NotFoundError, 404, "no run 'nowhere'"):
        run_pulls_answer(edge, "nowhere")


@pytest.mark.parametrize(("tier", "says"), [("cold", "restore it first"), ("deleted", "takes no data")])
def test_a_run_that_takes_no_data_is_not_pulled(edge: Edge, catalog: sessionmaker[Session], tier: str, says: str):
    add_run(catalog, "gone", tier=tier)
    with refused(ConflictError, 409, f"run 'gone' is {tier}", says):
        request_pull(edge, PullAsk("gone", [], [], None, None, None), "alice")


@pytest.mark.parametrize(
    ("part", "name", "says"),
    [
        ({"include": ["world/**"]}, "include", "'world/**' is not an entity path pattern"),
        ({"exclude": ["/a/**/b"]}, "exclude", "is not an entity path pattern"),
        ({"include": [f"/x{i}" for i in range(257)]}, "include", "257 patterns: at most 256"),
        ({"start": "10"}, "timeline", "start and end are positions on a timeline"),
        ({"end": "2026-11-21T08:00:00Z"}, "timeline", "name it too"),
        ({"timeline": "fr\x00me"}, "timeline", "NUL"),
        ({"timeline": "frame", "start": "x" * 2000}, "start", "over 1024 bytes"),
    ],
)
def test_a_part_that_is_not_is_refused_by_name(edge: Edge, run: str, part: dict[str, object], name: str, says: str):
    with refused(BadParameterError, 422, f"parameter '{name}'", says):
        request_pull(edge, PullAsk(RUN, **{**EVERYTHING, **part}), "alice")  # type: ignore[arg-type]


def test_empty_window_strings_are_no_window(edge: Edge, run: str):
    made = pull(edge, timeline="", start="", end="")
    assert (made["timeline"], made["start"], made["end"]) == (None, None, None)


# --- listing ----------------------------------------------------------------------------------------


def test_a_runs_pulls_newest_first(edge: Edge, run: str, clock: Clock):
    made = []
    for pattern in ("/a/**", "/b/**", "/c/**"):
        made.append(pull(edge, include=[pattern])["id"])
        clock.advance(seconds=1)
    assert [p["id"] for p in run_pulls_answer(edge, RUN)["pulls"]] == made[::-1]


def test_an_agent_polls_its_robots_pulls_oldest_first(edge: Edge, catalog: sessionmaker[Session], clock: Clock):
    add_run(catalog, RUN, robot=ROBOT)
    add_run(catalog, "theirs", robot=OTHER_ROBOT)
    mine = []
    for pattern in ("/a/**", "/b/**"):
        mine.append(pull(edge, include=[pattern])["id"])
        clock.advance(seconds=1)
    theirs = pull(edge, "theirs")["id"]
    progress(edge, mine[0], "sending")
    polled = pulls_answer(edge, robot_token(), PullQuery(state="pending"))["pulls"]
    assert [p["id"] for p in polled] == [mine[1]]  # its own robot's, by default; pending only
    everything = pulls_answer(edge, robot_token(), PullQuery())["pulls"]
    assert [p["id"] for p in everything] == mine
    assert [p["id"] for p in pulls_answer(edge, READER, PullQuery(limit=2))["pulls"]] == mine  # any robot, oldest first
    assert [p["id"] for p in pulls_answer(edge, ADMIN, PullQuery(robot=OTHER_ROBOT))["pulls"]] == [theirs]
    assert pulls_answer(edge, robot_token(), PullQuery(robot=ROBOT, state="done"))["pulls"] == []


def test_a_robot_token_polls_no_other_robots_pulls(edge: Edge):
    with refused(PermissionDeniedError, 403, f"robot '{ROBOT}' only", f"not those of robot '{OTHER_ROBOT}'"):
        pulls_answer(edge, robot_token(ROBOT), PullQuery(robot=OTHER_ROBOT))


@pytest.mark.parametrize(
    ("query", "name", "says"),
    [
        (PullQuery(state="waiting"), "state", "'waiting' is not one of pending, sending, done, failed, cancelled"),
        (PullQuery(limit=0), "limit", "0 is not between 1 and 1000"),
        (PullQuery(limit=1001), "limit", "1001 is not between 1 and 1000"),
    ],
)
def test_a_poll_that_is_not_is_refused_by_name(edge: Edge, query: PullQuery, name: str, says: str):
    with refused(BadParameterError, 422, f"parameter '{name}'", says):
        pulls_answer(edge, READER, query)


# --- progress and cancel ------------------------------------------------------------------------------


def test_progress_moves_a_pull_to_done(edge: Edge, run: str, clock: Clock):
    pull_id = str(pull(edge)["id"])
    clock.advance(seconds=5)
    sending = progress(edge, pull_id, "sending", 2, 2000)
    assert (sending["state"], sending["chunks_sent"], sending["bytes_sent"]) == ("sending", 2, 2000)
    assert sending["updated_at"] != sending["requested_at"]
    again = progress(edge, pull_id, "sending", 7, 7000)  # the same state: its counters only
    assert (again["state"], again["chunks_sent"], again["bytes_sent"]) == ("sending", 7, 7000)
    done = progress(edge, pull_id, "done", 9, 9000)
    assert (done["state"], done["chunks_sent"]) == ("done", 9)
    assert run_pulls_answer(edge, RUN)["pulls"][0] == done


@pytest.mark.parametrize("path", [["failed"], ["sending", "failed"]])
def test_a_pull_fails_from_pending_or_sending(edge: Edge, run: str, path: list[str]):
    pull_id = str(pull(edge)["id"])
    for state in path:
        last = progress(edge, pull_id, state, error="disk read error\x00" + "x" * 3000 if state == "failed" else None)
    assert last["state"] == "failed"
    assert str(last["error"]).startswith("disk read error\ufffd") and len(str(last["error"])) == MAX_ERROR_CHARS


def test_a_pull_is_sending_before_it_is_done(edge: Edge, run: str):
    pull_id = str(pull(edge)["id"])
    with refused(ConflictError, 409, f"pull '{pull_id}' is pending", "not done"):
        progress(edge, pull_id, "done")


@pytest.mark.parametrize(("final", "says"), [("done", "takes no more reports"), ("failed", "takes no more reports")])
def test_a_finished_pull_refuses_changes_naming_its_state(edge: Edge, run: str, final: str, says: str):
    pull_id = str(pull(edge)["id"])
    progress(edge, pull_id, "sending")
    progress(edge, pull_id, final)
    for state in ("sending", "done", "failed"):
        with refused(ConflictError, 409, f"pull '{pull_id}' is {final}", says):
            progress(edge, pull_id, state)
    with refused(ConflictError, 409, f"pull '{pull_id}' is {final} already"):
        cancel_pull(edge, pull_id)


def test_a_cancelled_pull_tells_its_agent_to_stop(edge: Edge, run: str):
    pending, sending = str(pull(edge, include=["/a/**"])["id"]), str(pull(edge, include=["/b/**"])["id"])
    progress(edge, sending, "sending", 1, 10)
    for pull_id in (pending, sending):
        assert cancel_pull(edge, pull_id)["pull"]["state"] == "cancelled"
        assert cancel_pull(edge, pull_id)["pull"]["state"] == "cancelled"  # again: as it is
        with refused(ConflictError, 409, f"pull '{pull_id}' is cancelled: stop sending it"):
            progress(edge, pull_id, "sending", 2, 20)
    assert pull(edge, include=["/a/**"])["id"] != pending  # cancelled: asking again queues a new one


def test_only_the_pulls_robot_or_a_writer_reports_progress(edge: Edge, run: str):
    pull_id = str(pull(edge)["id"])
    with refused(
        PermissionDeniedError, 403, f"pull '{pull_id}' belongs to robot '{ROBOT}'", f"robot '{OTHER_ROBOT}' only"
    ):
        progress(edge, pull_id, "sending", principal=robot_token(OTHER_ROBOT))
    assert progress(edge, pull_id, "sending", principal=WRITER)["state"] == "sending"
    assert progress(edge, pull_id, "done", principal=ADMIN)["state"] == "done"


def test_progress_says_what_an_agent_may_report(edge: Edge, run: str):
    pull_id = str(pull(edge)["id"])
    for state in ("pending", "cancelled", "finished"):
        with refused(BadParameterError, 422, "parameter 'state'", "is not one of sending, done, failed, held"):
            progress(edge, pull_id, state)


def test_an_unknown_pull_is_404(edge: Edge):
    with refused(NotFoundError, 404, "no pull 'pull-000000000000'", "fleet runs pulls RUN"):
        progress(edge, "pull-000000000000", "sending")
    with refused(NotFoundError, 404, "no pull 'pull-000000000000'"):
        cancel_pull(edge, "pull-000000000000")


def test_the_same_pull_asked_at_once_is_queued_once(edge: Edge, run: str):
    ask = PullAsk(RUN, ["/world/**"], [], None, None, None)
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda by: request_pull(edge, ask, by), [f"user-{i}" for i in range(6)]))
    assert len({answer["pull"]["id"] for answer, _ in answers}) == 1
    assert sorted(created for _, created in answers) == [False] * 5 + [True]
    assert len(run_pulls_answer(edge, RUN)["pulls"]) == 1
