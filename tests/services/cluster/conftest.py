"""A fresh Postgres catalog (migrated before any node starts: a non-embedded catalog is never
migrated by `fleet serve`), a SeaweedFS server with the bucket, and the cluster of nodes on them."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from catalog.db import create_engine, upgrade
from tests.postgres import temporary_database
from tests.seaweedfs import SeaweedFS
from tests.services.cluster.harness import Cluster

BUCKET = "fleet-cluster"


@pytest.fixture
def cluster_catalog_url() -> Iterator[str]:
    with temporary_database("fleet_cluster") as url:
        engine = create_engine(url)
        upgrade(engine)
        engine.dispose()
        yield url


@pytest.fixture
def weed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[SeaweedFS]:
    for name, value in (
        ("AWS_ACCESS_KEY_ID", "test"),
        ("AWS_SECRET_ACCESS_KEY", "test"),
        ("AWS_DEFAULT_REGION", "us-east-1"),
    ):
        monkeypatch.setenv(name, value)  # what the nodes' S3 clients read (they copy this environment)
    server = SeaweedFS(tmp_path / "weed").start()
    try:
        server.client().create_bucket(Bucket=BUCKET)
        yield server
    finally:
        server.stop()


@pytest.fixture
def cluster(tmp_path: Path, cluster_catalog_url: str, weed: SeaweedFS) -> Iterator[Cluster]:
    (tmp_path / "nodes").mkdir()
    nodes = Cluster(tmp_path / "nodes", cluster_catalog_url, weed, BUCKET)
    try:
        yield nodes
    finally:
        nodes.stop()
