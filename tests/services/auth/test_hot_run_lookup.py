"""What a list shows, its pages open: a run hot on this node that the catalog has no row of yet
(its stream just started or ended; the catalog flush runs every FLEET_CATALOG_FLUSH_S) is listed by
the overview from ingest's view, and `GET /v1/runs/RUN` and its console page answer from that view."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.console import app as console
from services.rrd.decoder import iter_events
from tests.services.api.nodes import migrated_settings, node
from tests.services.ingest.feeding import feed
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

RUN = "rec-points"


@pytest.fixture
def unflushed(tmp_path: Path, fresh_catalog_url: str) -> Iterator[TestClient]:
    """A depot (auth off: the console opens without a login) whose catalog flush does not come
    during the test."""
    with node(migrated_settings(tmp_path, catalog_url=fresh_catalog_url, catalog_flush_s=3600)) as client:
        console.install(client.app)  # type: ignore[arg-type]  # as `fleet serve` does
        yield client


def test_a_hot_run_the_catalog_lacks_yet_opens_as_it_is_listed(unflushed: TestClient, scenes: dict[str, Recording]):
    client = unflushed
    ingest = client.app.state.ingest  # type: ignore[attr-defined]
    source = ingest.open_source(live=True)
    feed(ingest, source, iter_events(scenes["points"].path))  # a stream still open: no catalog row yet
    assert client.get("/v1/runs").json()["runs"] == []  # the catalog's rows: none yet
    listed = client.get("/console/")  # the overview lists it from ingest's view
    assert listed.status_code == 200 and f"/console/runs/{RUN}" in listed.text, listed.text[:500]
    answer = client.get(f"/v1/runs/{RUN}")
    assert answer.status_code == 200, answer.text
    run = answer.json()
    assert (run["id"], run["tier"], run["status"]) == (RUN, "hot", "live")
    assert run["chunks"] > 0 and run["entities"] and run["events"] == [] and run["lifecycle"] is None
    page = client.get(f"/console/runs/{RUN}")
    assert page.status_code == 200 and RUN in page.text, page.text[:500]
    assert client.get("/v1/runs/no-such-run").status_code == 404
