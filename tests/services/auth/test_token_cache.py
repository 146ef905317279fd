"""The token cache (services/auth/token_cache.py): a record the catalog confirmed is used while the
catalog does not answer, up to the stale bound; after it, or for a token never confirmed, the check
is refused UNAVAILABLE; a hung lookup is waited for at most `wait_s`, once."""

from __future__ import annotations

import datetime as dt
import threading
import time

import pytest
import sqlalchemy as sa

from catalog.tokens import TokenRecord
from core.errors import CatalogUnavailableError
from services.auth.token_cache import TokenCache
from tests.waiting import wait_for

RECORD = TokenRecord(
    id="t1",
    name="n",
    subject="alice",
    scopes=("read",),
    robot_id=None,
    created_at=dt.datetime(2026, 1, 1, tzinfo=dt.UTC),
    created_by="admin",
    expires_at=None,
)


class Catalog:
    def __init__(self) -> None:
        self.mode = "up"
        self.release = threading.Event()

    def lookup(self, token_id: str) -> TokenRecord | None:
        if self.mode == "down":
            raise sa.exc.OperationalError("select", {}, Exception("connection refused"))
        if self.mode == "hung":
            self.release.wait(30)
            raise sa.exc.OperationalError("select", {}, Exception("cut"))
        return RECORD if token_id == "t1" else None


def test_a_confirmed_token_outlives_a_catalog_outage_up_to_the_stale_bound():
    catalog = Catalog()
    cache = TokenCache(catalog.lookup, fresh_s=0, stale_s=0.5, wait_s=0.3)
    assert cache.get("t1") == RECORD
    catalog.mode = "down"
    assert cache.get("t1") == RECORD  # confirmed a moment ago
    with pytest.raises(CatalogUnavailableError) as never_confirmed:
        cache.get("t2")
    assert never_confirmed.value.grpc_status() == "UNAVAILABLE" and never_confirmed.value.http_status() == 503

    def refused() -> bool:  # past the stale bound: refused, not let in unchecked
        try:
            cache.get("t1")
        except CatalogUnavailableError:
            return True
        return False

    wait_for(refused, 5, "a stale record to be refused past stale_s", interval=0.05)


def test_a_hung_catalog_is_waited_for_at_most_wait_s_and_only_once():
    catalog = Catalog()
    cache = TokenCache(catalog.lookup, fresh_s=0, stale_s=60, wait_s=0.3)
    assert cache.get("t1") == RECORD
    catalog.mode = "hung"
    try:
        started = time.monotonic()
        assert cache.get("t1") == RECORD
        first = time.monotonic() - started
        started = time.monotonic()
        assert cache.get("t1") == RECORD  # the lookup under way is not waited for again
        again = time.monotonic() - started
        assert 0.25 < first < 1.0 and again < 0.1, (first, again)
    finally:
        catalog.release.set()


def test_what_is_known_is_bounded_and_the_least_recently_used_token_is_asked_again():
    asked: list[str] = []

    def lookup(token_id: str) -> TokenRecord | None:
        asked.append(token_id)
        return RECORD if token_id == "t1" else None

    cache = TokenCache(lookup, fresh_s=60, stale_s=60, max_tokens=2)
    assert cache.get("t1") == RECORD and cache.get("t2") is None
    assert cache.get("t1") == RECORD and asked == ["t1", "t2"]  # both known
    assert cache.get("t3") is None  # t2, used least recently, makes room
    assert cache.get("t1") == RECORD and cache.get("t2") is None
    assert asked == ["t1", "t2", "t3", "t2"]
