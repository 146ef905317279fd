"""The runs REST API on a real `fleet serve` after real recordings were uploaded."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.live_server import LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]) -> Iterator[LiveServer]:
    live = LiveServer(Path(tmp_path_factory.mktemp("runs-api")) / "data").start()
    for name in ("points", "properties", "image"):
        assert httpx.post(f"{live.url}/v1/uploads", content=recordings[name].data, timeout=60).status_code == 200
    yield live
    live.stop()


def test_runs_list_and_detail(server: LiveServer, recordings: dict[str, Recording]):
    listed = httpx.get(f"{server.url}/v1/runs", timeout=30).json()
    ids = {r["id"] for r in listed["runs"]}
    expected = {recordings[n].recordings[0]["recording_id"] for n in ("points", "properties", "image")}
    assert ids == expected and listed["next_cursor"] is None
    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    detail = httpx.get(f"{server.url}/v1/runs/{run_id}", timeout=30).json()
    assert detail["status"] == "closed" and detail["tier"] == "hot" and detail["sdk_version"] == "0.41.0"
    assert {e["path"] for e in detail["entities"]} == set(rec.recordings[0]["entities"])
    truth_timelines = {t for e in rec.recordings[0]["entities"].values() for t in e["timelines"]} | {"log_time"}
    assert {t["name"] for t in detail["timelines"]} == truth_timelines
    page = httpx.get(f"{server.url}/v1/runs", params={"limit": 2}, timeout=30).json()
    rest = httpx.get(f"{server.url}/v1/runs", params={"limit": 2, "cursor": page["next_cursor"]}, timeout=30).json()
    assert {r["id"] for r in page["runs"] + rest["runs"]} == expected
    robots = httpx.get(f"{server.url}/v1/robots", timeout=30).json()["robots"]
    assert sum(r["runs"] for r in robots) == 3


def test_errors(server: LiveServer):
    missing = httpx.get(f"{server.url}/v1/runs/no-such-run", timeout=30)
    assert missing.status_code == 404 and "no-such-run" in missing.json()["message"]
    for params, name in (
        ({"limit": "many"}, "limit"),
        ({"limit": 5000}, "limit"),
        ({"sort": "x"}, "sort"),
        ({"since": "yesterday"}, "since"),
        ({"sort": "id", "cursor": "W3t9LCAxXQ"}, "cursor"),
        ({"entity": ["/world/x"] * 1000}, "entity"),
    ):
        bad = httpx.get(f"{server.url}/v1/runs", params=params, timeout=30)
        assert bad.status_code == 422, params
        assert bad.json()["code"] == "INVALID_ARGUMENT" and f"'{name}'" in bad.json()["message"]
    quoted = httpx.get(f"{server.url}/v1/runs", params={"property": 'a"b.c=1'}, timeout=30)
    assert quoted.status_code == 200 and quoted.json()["runs"] == [], quoted.text
