"""Fixtures of the auth suites: a token service on a catalog of its own, and a depot with auth on
(each on DuckDB and Postgres); tokens of every kind; small runs logged with the real SDK."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy.orm import Session, sessionmaker

from services.auth.keys import SigningKey, SigningKeys
from services.auth.tokens import Auth, IssuedToken
from tests.services.api.nodes import migrated_settings, node
from tests.services.rrd.recordings import Recording

KEYS = SigningKeys(SigningKey(b"k" * 48))
OTHER_KEYS = SigningKeys(SigningKey(b"o" * 48))
HOSTS = ["depot.example", "127.0.0.1"]


@pytest.fixture
def auth(catalog: sessionmaker[Session]) -> Auth:
    return Auth(enabled=True, keys=KEYS, catalog=catalog, public_hosts=HOSTS)


# --- a depot (the app as `fleet serve` wires it) with auth on, and tokens of each scope ----------


@dataclass
class Depot:
    client: TestClient

    @property
    def app(self) -> FastAPI:
        app = self.client.app
        assert isinstance(app, FastAPI)
        return app

    @property
    def auth(self) -> Auth:
        auth: Auth = self.app.state.auth
        return auth

    def issue(self, *scopes: str, robot: str | None = None, name: str | None = None) -> IssuedToken:
        return self.auth.issue(subject=name or robot or "-".join(scopes), scopes=scopes, robot=robot, created_by="test")

    def token(self, *scopes: str, robot: str | None = None, name: str | None = None) -> str:
        return self.issue(*scopes, robot=robot, name=name).token

    def expired_token(self, *scopes: str) -> str:
        """A token of this depot that expired an hour ago (issued by a node whose clock was behind)."""
        behind = Auth(
            enabled=True,
            keys=self.auth.keys,
            catalog=self.auth.catalog,
            clock=lambda: dt.datetime.now(dt.UTC) - dt.timedelta(hours=2),
        )
        return behind.issue(subject="late", scopes=scopes, created_by="test", expires_in=dt.timedelta(hours=1)).token

    def revoked_token(self, *scopes: str) -> str:
        issued = self.issue(*scopes, name="revoked")
        self.auth.revoke(issued.record.id, "test")
        return issued.token

    def failures(self, surface: str, reason: str) -> float:
        """fleet_auth_failures_total{surface, reason} as /metrics shows it (asked with a read token)."""
        text = self.client.get("/metrics", headers=bearer(self.token("read"))).text
        for family in text_string_to_metric_families(text):
            for sample in family.samples:
                if sample.name == "fleet_auth_failures_total" and sample.labels == {
                    "surface": surface,
                    "reason": reason,
                }:
                    return sample.value
        return 0.0


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@contextmanager
def open_depot(tmp_path: Path, catalog_url: str, **settings: Any) -> Iterator[Depot]:
    # A busy machine can take seconds to open a fresh database's first connection: a token check
    # waits for it here (the tests of a catalog that does not answer set their own wait).
    settings.setdefault("auth_catalog_wait_s", 30.0)
    with node(migrated_settings(tmp_path, auth="on", catalog_url=catalog_url, **settings)) as client:
        yield Depot(client)


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url) as opened:
        yield opened


# --- small runs logged with the real rerun-sdk ------------------------------------------------------

# "points" names no robot; "properties" says fleet.robot_id = robot-7 (and carries a token field).
SCENES = ("points", "properties")


@pytest.fixture(scope="session")
def scenes(recordings: dict[str, Recording]) -> dict[str, Recording]:
    return {name: recordings[name] for name in SCENES}
