"""`/readyz` means ready: the catalog answers and the hot disk takes writes; otherwise 503 naming
what is not ready."""

from __future__ import annotations

import asyncio
import shutil
import threading
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from services.api import readiness
from services.settings import load_settings
from tests.services.api.nodes import migrated_settings, node
from tests.subprocess_server import free_port


def not_ready(client: TestClient) -> dict[str, Any]:
    response = client.get("/readyz")
    assert response.status_code == 503, response.text
    body: dict[str, Any] = response.json()
    assert body["status"] == "not ready" and body["code"] == "UNAVAILABLE"
    return body


def test_a_working_node_is_ready(tmp_path: Path):
    with node(migrated_settings(tmp_path)) as client:
        response = client.get("/readyz")
        assert response.status_code == 200, response.text
        assert response.json() == {"status": "ready", "checks": {"catalog": "ok", "hot_disk": "ok"}}
        assert not [p for p in (tmp_path / "data" / "hot").iterdir()]  # the probe's file is gone


def test_an_unreachable_postgres_catalog_is_named(tmp_path: Path):
    settings = load_settings(
        data_dir=tmp_path / "data",
        scheduler=False,
        catalog_url=f"postgresql+psycopg://fleet@127.0.0.1:{free_port()}/fleet",
    )
    with node(settings) as client:
        body = not_ready(client)
        assert body["not_ready"] == ["catalog"]
        assert body["checks"]["hot_disk"] == "ok"
        assert body["checks"]["catalog"].startswith("OperationalError: "), body
        assert "catalog" in body["message"]


def test_an_embedded_catalog_that_cannot_be_opened_is_named(tmp_path: Path):
    settings = migrated_settings(tmp_path)
    with node(settings) as client:
        assert client.get("/readyz").status_code == 200
        client.app.state.node.catalog.kw["bind"].dispose()  # type: ignore[attr-defined]
        path = Path(settings.catalog_url.removeprefix("duckdb:///"))
        path.unlink()
        path.mkdir()  # the catalog's file is gone and nothing can open one there
        body = not_ready(client)
        assert body["not_ready"] == ["catalog"] and body["checks"]["hot_disk"] == "ok"


def test_a_hot_dir_that_takes_no_writes_is_named(tmp_path: Path):
    settings = migrated_settings(tmp_path)
    with node(settings) as client:
        shutil.rmtree(settings.hot_dir)
        settings.hot_dir.write_bytes(b"")  # a file where the hot runs' folder was: nothing can be created in it
        body = not_ready(client)
        assert body["not_ready"] == ["hot_disk"] and body["checks"]["catalog"] == "ok"
        assert str(settings.hot_dir) in body["checks"]["hot_disk"]


def test_a_hot_disk_below_the_free_space_guard_is_named(tmp_path: Path):
    free = shutil.disk_usage(tmp_path).free
    with node(migrated_settings(tmp_path, min_free_bytes=free * 2)) as client:
        body = not_ready(client)
        assert body["not_ready"] == ["hot_disk"]
        assert "FLEET_MIN_FREE_BYTES" in body["checks"]["hot_disk"]


def test_a_hung_check_answers_within_its_limit_and_is_not_started_twice():
    release, calls = threading.Event(), []

    def hangs() -> None:
        calls.append(1)
        release.wait(30)

    check = readiness.Check("slow", hangs)
    try:
        assert asyncio.run(check.status(timeout=0.05)) == "no answer within 0.05 s"
        assert asyncio.run(check.status(timeout=0.05)) == "no answer within 0.05 s"
        assert len(calls) == 1  # the second probe did not start a second thread
    finally:
        release.set()
    assert asyncio.run(check.status(timeout=5)) == "ok"  # once it returns, the check answers again
