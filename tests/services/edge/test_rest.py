"""The edge routes through the app as `fleet serve` wires it, with auth on, called with the REST
client (`sdk_client`) a robot's agent and the CLI use: the answers' shapes, statuses, and who may
call what."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from sdk_client.rest import FleetClient, ServiceError
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.edge.conftest import OTHER_ROBOT, ROBOT, RUN, SdkRuns, add_run, chunk_ids

PULLED = "pulled-over-rest"


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url) as opened:
        yield opened


def sdk(depot: Depot, token: str) -> FleetClient:
    """The REST client with `token`, talking to the app in this process."""
    fleet = FleetClient("http://testserver", token=token)
    fleet.close()
    fleet._http = TestClient(depot.app, base_url="http://testserver", headers=dict(fleet._http.headers))
    return fleet


def catalog(depot: Depot) -> sessionmaker[Session]:
    found: sessionmaker[Session] = depot.app.state.catalog
    return found


def refused(call, status: int, *says: str) -> None:
    with pytest.raises(ServiceError) as info:
        call()
    assert info.value.status == status, info.value.body
    for text in says:
        assert text in info.value.message, info.value.message


@pytest.mark.sdk
def test_a_robot_asks_what_the_depot_holds_of_its_run(depot: Depot, sdk_runs: SdkRuns):
    robot = sdk(depot, depot.token("ingest", robot=ROBOT))
    ids = chunk_ids(sdk_runs.first)
    assert robot.held(RUN, ids)["missing"] == ids  # not sent yet: all missing
    robot.upload(sdk_runs.first)
    hot = robot.held(RUN, [*ids, "0" * 32])
    holder = hot.pop("holder")
    assert holder.startswith("depot/")  # this depot process: agents ask again if that changes
    assert robot.held(RUN, ids[:1])["holder"] == holder
    assert hot == {
        "run": RUN,
        "robot": ROBOT,
        "tier": "hot",
        "status": "closed",
        "accepts_data": True,
        "missing": ["0" * 32],
        "unsealed": ids,
        "sealed": 0,
    }
    refused(lambda: sdk(depot, depot.token("ingest", robot=OTHER_ROBOT)).held(RUN, ids), 403, ROBOT, OTHER_ROBOT)
    assert sdk(depot, depot.token("read")).held(RUN, ids)["unsealed"] == ids
    sdk(depot, depot.token("write")).promote(RUN)
    sealed = robot.held(RUN, ids)
    assert (sealed["tier"], sealed["missing"], sealed["unsealed"], sealed["sealed"]) == ("warm", [], [], len(ids))
    assert sealed["holder"] is None


def test_held_refuses_what_is_no_chunk_id(depot: Depot):
    robot = sdk(depot, depot.token("ingest", robot=ROBOT))
    refused(lambda: robot.held(RUN, ["XYZ"]), 422, "parameter 'chunk_ids'", "item 0 ('XYZ') is not a chunk id")
    refused(lambda: robot.held(RUN, []), 422, "no chunk ids")
    answer = depot.client.post(
        f"/v1/runs/{RUN}/held", json={"chunk_ids": ["0" * 32], "ids": []}, headers=bearer(depot.token("read"))
    )
    assert answer.status_code == 422 and "parameter 'ids'" in answer.json()["message"]


def test_an_engineer_pulls_and_a_robot_sends(depot: Depot):
    add_run(catalog(depot), PULLED, robot=ROBOT)
    alice_token = depot.token("write", name="alice")
    alice, robot = sdk(depot, alice_token), sdk(depot, depot.token("ingest", robot=ROBOT))
    pull = alice.request_pull(PULLED, include=["/world/**"], timeline="frame", start="10", end="20")
    assert (pull["state"], pull["robot_id"], pull["requested_by"]) == ("pending", ROBOT, "alice")
    assert alice_token not in str(pull)
    body = {"include": ["/world/**"], "timeline": "frame", "start": "10", "end": "20"}
    twin = depot.client.post(f"/v1/runs/{PULLED}/pull", json=body, headers=bearer(alice_token))
    assert twin.status_code == 200 and twin.json() == {"pull": pull}  # the same pull, not a twin
    other = depot.client.post(f"/v1/runs/{PULLED}/pull", json={"exclude": ["/x"]}, headers=bearer(alice_token))
    assert other.status_code == 202 and other.json()["pull"]["id"] != pull["id"]
    assert [p["id"] for p in robot.pulls(state="pending")] == [pull["id"], other.json()["pull"]["id"]]
    refused(lambda: robot.pulls(robot=OTHER_ROBOT), 403, f"robot '{ROBOT}' only", OTHER_ROBOT)
    refused(
        lambda: sdk(depot, depot.token("ingest", robot=OTHER_ROBOT)).pull_progress(
            pull["id"], state="sending", chunks_sent=0, bytes_sent=0
        ),
        403,
        f"belongs to robot '{ROBOT}'",
    )
    assert robot.pull_progress(pull["id"], state="sending", chunks_sent=3, bytes_sent=3000)["state"] == "sending"
    done = robot.pull_progress(pull["id"], state="done", chunks_sent=5, bytes_sent=5000)
    assert (done["state"], done["chunks_sent"], done["bytes_sent"]) == ("done", 5, 5000)
    refused(lambda: robot.pull_progress(pull["id"], state="sending", chunks_sent=6, bytes_sent=1), 409, "is done")
    assert alice.cancel_pull(other.json()["pull"]["id"])["state"] == "cancelled"
    listed = sdk(depot, depot.token("read")).run_pulls(PULLED)
    assert [(p["id"], p["state"]) for p in listed] == [(other.json()["pull"]["id"], "cancelled"), (pull["id"], "done")]
    refused(lambda: alice.request_pull("no-such-run"), 404, "no run 'no-such-run'")
    refused(lambda: alice.request_pull(PULLED, start="10"), 422, "parameter 'timeline'")
    refused(lambda: robot.pull_progress(pull["id"], state="done", chunks_sent=-1, bytes_sent=0), 422, "chunks_sent")


def test_a_robot_reports_its_copy_and_the_run_page_shows_it(depot: Depot):
    add_run(catalog(depot), PULLED, robot=ROBOT)
    robot, reader = sdk(depot, depot.token("ingest", robot=ROBOT)), sdk(depot, depot.token("read"))
    keeps = dt.datetime(2026, 11, 25, 8, 0, tzinfo=dt.UTC)
    copy = robot.report_robot_copy(
        PULLED,
        chunks=10,
        bytes=1000,
        local_only_chunks=4,
        local_only_bytes=400,
        local_only_entities=["/camera"],
        keeps_until=keeps,
    )
    assert copy["keeps_until"] == "2026-11-25T08:00:00Z" and copy["local_only_entities"] == ["/camera"]
    pull = sdk(depot, depot.token("write")).request_pull(PULLED, include=["/camera"])
    page = reader.run(PULLED)
    assert page["robot_copy"] == copy and page["pulls"] == [pull]
    refused(
        lambda: sdk(depot, depot.token("write")).report_robot_copy(PULLED, chunks=1, bytes=1),
        403,
        "'ingest' or 'admin'",
    )
    refused(lambda: robot.report_robot_copy("not-yet", chunks=1, bytes=1), 404, "retry later")
    refused(lambda: robot.report_robot_copy(PULLED, chunks=1), 422, "parameter 'bytes'")
    assert robot.forget_robot_copy(PULLED) == {"run": PULLED, "removed": True, "robot_copy": None}
    assert reader.run(PULLED)["robot_copy"] is None
