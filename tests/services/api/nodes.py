"""The app as `fleet serve` wires it (ingest, retention, analytics), as a test client."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from catalog.db import create_engine, upgrade
from services.api.app import create_app
from services.server import build
from services.settings import Settings, load_settings


@contextmanager
def node(settings: Settings) -> Iterator[TestClient]:
    built = build(settings)
    try:
        with TestClient(create_app(built.node, built.ingest, built.retention, built.analytics)) as client:
            yield client
    finally:
        built.node.hot.close()
        built.node.catalog.kw["bind"].dispose()


def migrated_settings(tmp_path: Path, **overrides: Any) -> Settings:
    """Settings of a node under `tmp_path`, its embedded catalog migrated."""
    settings = load_settings(data_dir=tmp_path / "data", scheduler=False, **overrides)
    engine = create_engine(settings.catalog_url)
    upgrade(engine)
    engine.dispose()
    return settings
