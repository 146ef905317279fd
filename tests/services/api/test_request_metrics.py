"""`/metrics` counts HTTP requests by route template and status, with their latency."""

from __future__ import annotations

import re
from pathlib import Path

from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from services.api.app import create_app
from services.server import open_node
from services.settings import load_settings


def test_requests_are_counted_by_route_template_and_status(tmp_path: Path):
    client = TestClient(create_app(open_node(load_settings(data_dir=tmp_path))))
    for _ in range(2):
        assert client.get("/healthz").status_code == 200
    for path in ("/no/such/page", "/another/made-up/path"):
        assert client.get(path).status_code == 404
    text = client.get("/metrics").text
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }

    def requests(route: str, status: str) -> float:
        return samples.get(
            ("fleet_http_requests_total", (("method", "GET"), ("route", route), ("status", status))), 0.0
        )

    assert requests("/healthz", "200") == 2
    assert requests("unmatched", "404") == 2  # made-up paths add no series of their own
    assert not any("made-up" in str(labels) for _, labels in samples)
    assert samples[("fleet_http_request_seconds_count", (("method", "GET"), ("route", "/healthz")))] == 2
    for name in ("fleet_http_requests", "fleet_http_request_seconds"):
        assert re.search(rf"^# HELP {name}(_total)? \S", text, re.MULTILINE), name
