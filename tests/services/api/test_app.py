"""The REST app's own pages: API docs that work offline, and the Prometheus exposition."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from services.api.app import create_app
from services.server import open_node
from services.settings import load_settings
from tests.services.api.nodes import migrated_settings
from tests.services.api.nodes import node as node_of
from tests.services.rrd.recordings import Recording

ASSET_TYPES = {".js": "javascript", ".css": "text/css", ".png": "image/png"}


@pytest.fixture
def node(tmp_path: Path) -> Iterator[TestClient]:
    """The app as `fleet serve` wires it (ingest, retention, analytics), as a test client."""
    with node_of(migrated_settings(tmp_path)) as client:
        yield client


def _referenced_urls(html: str) -> list[str]:
    return re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", html)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_api_docs_load_only_from_the_service(tmp_path: Path, page: str):
    """A depot without internet still shows its API docs: every script, style and icon the page
    loads is served by the service itself, and nothing names another host."""
    client = TestClient(create_app(open_node(load_settings(data_dir=tmp_path))))
    response = client.get(page)
    assert response.status_code == 200
    html = response.text
    urls = _referenced_urls(html)
    assert any(u.endswith(".js") for u in urls), urls
    assert "://" not in html.replace("window.location.origin", ""), "the page names another host"
    for url in urls:
        assert url.startswith("/") and not url.startswith("//"), url
        asset = client.get(url)
        assert asset.status_code == 200, url
        assert ASSET_TYPES[Path(url).suffix] in asset.headers["content-type"], (url, asset.headers["content-type"])
        assert len(asset.content) > 1000, url
    assert client.get("/openapi.json").status_code == 200


def test_swagger_ui_sends_the_spec_to_no_validator(tmp_path: Path):
    html = TestClient(create_app(open_node(load_settings(data_dir=tmp_path)))).get("/docs").text
    assert '"validatorUrl": null' in html


@pytest.mark.sdk
def test_metrics_have_help_and_type_and_count_what_was_ingested(node: TestClient, recordings: dict[str, Recording]):
    answer = node.post("/v1/uploads", content=recordings["points"].data)
    assert answer.status_code == 200, answer.text
    report = answer.json()
    response = node.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain; version=0.0.4")
    text = response.text
    families = {f.name: f for f in text_string_to_metric_families(text)}
    for name in (
        "fleet_build_info",
        "fleet_live_streams",
        "fleet_hot_runs",
        "fleet_live_runs",
        "fleet_ingest_chunks_new",
        "fleet_ingest_chunks_duplicate",
        "fleet_ingest_bytes_new",
        "fleet_ingest_messages",
    ):
        assert name in families, name
    for name in families:  # every metric documented, in the text itself
        assert re.search(rf"^# HELP {name}(_total)? \S", text, re.MULTILINE), name
        assert re.search(rf"^# TYPE {name}(_total)? \w", text, re.MULTILINE), name
    assert families["fleet_ingest_chunks_new"].type == "counter"
    assert families["fleet_hot_runs"].type == "gauge"

    def sample(metric: str) -> float:
        return next(s.value for f in families.values() for s in f.samples if s.name == metric)

    assert sample("fleet_ingest_chunks_new_total") == report["chunks_new"] > 0
    assert sample("fleet_ingest_chunks_duplicate_total") == report["chunks_duplicate"]
    assert sample("fleet_hot_runs") == 1
    assert re.search(r'^fleet_build_info\{version="[^"]+"\} 1', text, re.MULTILINE)
