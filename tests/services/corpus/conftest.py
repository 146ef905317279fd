"""A depot with auth on (the app as `fleet serve` wires it) and the REST client on it; runs written
to its catalog as ingest would, with the timelines annotations are checked against."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.queries import TimelineRecord
from sdk_client.rest import FleetClient, ServiceError
from tests.catalog.records import run_record
from tests.services.auth.conftest import Depot, open_depot

T0 = 1_780_000_000_000_000_000  # a log_time in ns (2026)
TIMELINES = [
    TimelineRecord("log_time", "timestamp", T0, T0 + 60_000_000_000),
    TimelineRecord("frame", "sequence", 0, 600),
]


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url) as opened:
        yield opened


def sdk(depot: Depot, token: str) -> FleetClient:
    """The REST client with `token`, talking to the app in this process."""
    from fastapi.testclient import TestClient

    fleet = FleetClient("http://testserver", token=token)
    fleet.close()
    fleet._http = TestClient(depot.app, base_url="http://testserver", headers=dict(fleet._http.headers))
    return fleet


def catalog_of(depot: Depot) -> sessionmaker[Session]:
    found: sessionmaker[Session] = depot.app.state.catalog
    return found


def add_run(depot: Depot, run_id: str, robot: str = "robot-7") -> None:
    """A closed run with a log_time (timestamp) and a frame (sequence) timeline."""
    now = dt.datetime.now(dt.UTC)
    with session_scope(catalog_of(depot), write=True) as session:
        queries.save_run(session, run_record(run_id, robot_id=robot, timelines=list(TIMELINES)), now)


def refused(call: Callable[[], Any], status: int, *says: str) -> ServiceError:
    with pytest.raises(ServiceError) as info:
        call()
    assert info.value.status == status, info.value.body
    for text in says:
        assert text in info.value.message, info.value.message
    return info.value
