"""REST of saved queries (`/v1/queries`) in process, with the SQL run by the real workers."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from services.analytics import queries_rest, saved
from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.services.analytics.conftest import api
from tests.services.retention.conftest import NodeFactory


def _client(tmp_path: Path, make_node: NodeFactory) -> TestClient:
    node = make_node(Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri())))
    client = api(node)
    client.app.include_router(queries_rest.router)  # type: ignore[attr-defined]
    return client


def test_save_list_answer_and_delete(tmp_path: Path, make_node: NodeFactory) -> None:
    client = _client(tmp_path, make_node)
    assert client.get("/v1/queries").json() == {"queries": []}
    made = client.post(
        "/v1/queries", json={"name": "numbers", "sql": "SELECT x, x * x AS y FROM range(4) t(x)", "chart": "line"}
    )
    assert made.status_code == 201, made.text
    query = made.json()
    assert (query["name"], query["chart"], query["created_by"]) == ("numbers", "line", "local")
    assert query["id"].startswith("q-") and query["created_at"].endswith("Z")
    assert [q["id"] for q in client.get("/v1/queries").json()["queries"]] == [query["id"]]

    got = client.get(f"/v1/queries/{query['id']}")
    assert got.status_code == 200, got.text
    assert got.json()["answer"]["rows"] == [[0, 0], [1, 1], [2, 4], [3, 9]]

    taken = client.post("/v1/queries", json={"name": "numbers", "sql": "SELECT 1 AS one"})
    assert taken.status_code == 409, taken.text
    assert taken.json()["code"] == "ALREADY_EXISTS" and "already named 'numbers'" in taken.json()["message"]

    bad = client.post("/v1/queries", json={"name": "broken", "sql": "SELEC nothing"})
    assert bad.status_code == 400, bad.text  # a query that does not run is not saved
    assert bad.json()["code"] == "INVALID_SQL"
    assert [q["name"] for q in client.get("/v1/queries").json()["queries"]] == ["numbers"]

    gone = client.delete(f"/v1/queries/{query['id']}")
    assert gone.status_code == 200 and gone.json()["deleted"]["name"] == "numbers"
    assert client.delete(f"/v1/queries/{query['id']}").status_code == 404
    assert client.get(f"/v1/queries/{query['id']}").status_code == 404
    assert client.get("/v1/queries").json() == {"queries": []}


def test_the_example_runs_and_charts_follow_the_columns(tmp_path: Path, make_node: NodeFactory) -> None:
    client = _client(tmp_path, make_node)
    ctx = client.app.state.analytics  # type: ignore[attr-defined]
    assert saved.answer(saved.run_sql(ctx, saved.EXAMPLE)).columns == ("robot_day", "drain_volts")
    line = saved.answer(saved.run_sql(ctx, "SELECT x, x * 2.5 AS y FROM range(3) t(x) ORDER BY x DESC")).chart
    assert line is not None and line.kind == "line" and line.points == [(0, 0), (1, 2.5), (2, 5)]
    bars = saved.answer(saved.run_sql(ctx, "SELECT 'r' || x AS robot, x AS n FROM range(3) t(x)")).chart
    assert bars is not None and bars.kind == "bar" and bars.labels == ("r0", "r1", "r2") and bars.ys == (0, 1, 2)
    days = saved.answer(saved.run_sql(ctx, "SELECT DATE '2026-03-01' + x::INTEGER AS day, x AS n FROM range(2) t(x)"))
    assert days.chart is not None and days.chart.x_format == "time_ns"
    assert days.chart.xs == (1_772_323_200e9, 1_772_409_600e9)
    assert saved.answer(saved.run_sql(ctx, "SELECT 1 AS a, 'x' AS b")).chart is None  # second column not a number
    many = saved.answer(saved.run_sql(ctx, "SELECT x FROM range(1500) t(x)"))
    assert (many.total, len(many.rows), many.truncated) == (1500, saved.MAX_SHOWN, True)
