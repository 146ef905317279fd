"""A robot's ingest token writes its own robot's runs and reads nothing."""

from __future__ import annotations

import pytest

from tests.services.auth.conftest import Depot, bearer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

ROBOT_A = "robot-a"
ROBOT_B = "robot-7"  # the robot the "properties" scene names in its fleet property


def _run(depot: Depot, run_id: str) -> dict[str, object]:
    answer = depot.client.get(f"/v1/runs/{run_id}", headers=bearer(depot.token("read")))
    assert answer.status_code == 200, answer.text
    run: dict[str, object] = answer.json()
    return run


def test_a_robot_token_cannot_upload_another_robots_run(depot: Depot, scenes: dict[str, Recording]):
    answer = depot.client.post(
        "/v1/uploads", content=scenes["properties"].data, headers=bearer(depot.token("ingest", robot=ROBOT_A))
    )
    assert answer.status_code == 403, answer.text
    message = answer.json()["message"]
    assert answer.json()["code"] == "PERMISSION_DENIED" and ROBOT_A in message and ROBOT_B in message
    run = depot.client.get("/v1/runs/rec-properties", headers=bearer(depot.token("read")))
    assert run.status_code == 404 or run.json()["robot_id"] != ROBOT_B  # never filed as robot B's


def test_the_robot_a_run_names_may_upload_it(depot: Depot, scenes: dict[str, Recording]):
    own = depot.client.post(
        "/v1/uploads", content=scenes["properties"].data, headers=bearer(depot.token("ingest", robot=ROBOT_B))
    )
    assert own.status_code == 200, own.text
    assert _run(depot, "rec-properties")["robot_id"] == ROBOT_B


def test_nothing_of_a_run_refused_to_a_robot_token_is_kept(depot: Depot, scenes: dict[str, Recording]):
    robot = bearer(depot.token("ingest", robot=ROBOT_A))
    assert depot.client.post("/v1/uploads", content=scenes["properties"].data, headers=robot).status_code == 403
    reader = bearer(depot.token("read"))
    assert depot.client.get("/v1/runs", headers=reader).json()["runs"] == []
    own = bearer(depot.token("ingest", robot=ROBOT_B))
    assert depot.client.post("/v1/uploads", content=scenes["properties"].data, headers=own).status_code == 200


def test_a_run_that_names_no_robot_is_filed_under_the_tokens_robot(depot: Depot, scenes: dict[str, Recording]):
    answer = depot.client.post(
        "/v1/uploads", content=scenes["points"].data, headers=bearer(depot.token("ingest", robot=ROBOT_A))
    )
    assert answer.status_code == 200, answer.text
    assert _run(depot, "rec-points")["robot_id"] == ROBOT_A
    robots = depot.client.get("/v1/robots", headers=bearer(depot.token("read"))).json()["robots"]
    assert [r["id"] for r in robots] == [ROBOT_A]


def test_a_write_token_uploads_for_any_robot(depot: Depot, scenes: dict[str, Recording]):
    answer = depot.client.post("/v1/uploads", content=scenes["properties"].data, headers=bearer(depot.token("write")))
    assert answer.status_code == 200, answer.text
    assert _run(depot, "rec-properties")["robot_id"] == ROBOT_B


def test_a_robot_token_reads_nothing_not_even_its_own_runs(depot: Depot, scenes: dict[str, Recording]):
    robot = bearer(depot.token("ingest", robot=ROBOT_A))
    assert depot.client.post("/v1/uploads", content=scenes["points"].data, headers=robot).status_code == 200
    reads = [
        ("GET", "/v1/robots", {}),
        ("GET", "/v1/runs", {}),
        ("GET", "/v1/runs/rec-points", {}),
        ("GET", "/v1/runs/rec-points/recording.rrd", {}),
        ("POST", "/v1/runs/rec-points/links", {}),
        ("POST", "/v1/sql", {"json": {"query": "SELECT * FROM runs"}}),
        ("GET", "/metrics", {}),
        ("GET", "/v1/retention", {}),
    ]
    for method, path, extra in reads:
        answer = depot.client.request(method, path, headers=robot, **extra)
        assert answer.status_code == 403, (path, answer.text)
        assert "needs the 'read' scope" in answer.json()["message"]
    assert depot.client.get("/v1/runs/rec-points/recording.rrd", headers=bearer(depot.token("read"))).status_code == 200


def test_a_refused_upload_answers_what_was_kept_not_what_was_dropped(depot: Depot, scenes: dict[str, Recording]):
    robot = bearer(depot.token("ingest", robot=ROBOT_A))
    answer = depot.client.post("/v1/uploads", content=scenes["properties"].data, headers=robot)
    assert answer.status_code == 403, answer.text
    accepted = answer.json()["accepted"]
    assert accepted["runs"] == [] and accepted["dropped"] == ["rec-properties"], accepted
    assert (accepted["chunks_new"], accepted["bytes_new"]) == (0, 0), accepted  # the run went whole


@pytest.mark.parametrize("sealed", [False, True], ids=["hot", "sealed"])
def test_another_robots_token_cannot_upload_an_existing_run_again(
    depot: Depot, scenes: dict[str, Recording], sealed: bool
):
    robot_a = bearer(depot.token("ingest", robot=ROBOT_A))
    own = depot.client.post("/v1/uploads", content=scenes["points"].data, headers=robot_a)
    assert own.status_code == 200, own.text
    if sealed:
        assert depot.client.post("/v1/runs/rec-points/promote", headers=bearer(depot.token("write"))).status_code == 200
    other = bearer(depot.token("ingest", robot=ROBOT_B))
    again = depot.client.post("/v1/uploads", content=scenes["points"].data, headers=other)
    assert again.status_code == 403, again.text  # not 200 "0 new": the run is robot A's
    assert again.json()["code"] == "PERMISSION_DENIED" and ROBOT_A in again.json()["message"]
    assert _run(depot, "rec-points")["robot_id"] == ROBOT_A
