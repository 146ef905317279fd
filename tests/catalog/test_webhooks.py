"""Webhooks and their outbox in the catalog (`catalog.webhooks`), identical on DuckDB and Postgres."""

from __future__ import annotations

import datetime as dt
import json

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import webhooks
from catalog.db import session_scope
from catalog.webhooks import DELIVERED, FAILED, PENDING, WebhookRecord
from core.errors import InvalidArgumentError, NotFoundError

T0 = dt.datetime(2026, 11, 23, 8, tzinfo=dt.UTC)
HOLD = dt.timedelta(seconds=30)


def hook(webhook_id: str, *on: str, body_format: str = "json", at: dt.datetime = T0) -> WebhookRecord:
    return WebhookRecord(webhook_id, f"http://hooks.example/{webhook_id}", on, body_format, "sealed!", "alice", at)


def add(catalog: sessionmaker[Session], *records: WebhookRecord) -> None:
    with session_scope(catalog, write=True) as session:
        for record in records:
            webhooks.add_webhook(session, record)


def enqueue(catalog: sessionmaker[Session], occurrence: str, occurrence_id: str, **payload: object) -> int:
    with session_scope(catalog, write=True) as session:
        return webhooks.enqueue(session, occurrence, occurrence_id, dict(payload), now=T0)


def test_webhooks_are_added_listed_and_removed_with_their_deliveries(catalog: sessionmaker[Session]) -> None:
    add(catalog, hook("wh-a", "run.sealed"), hook("wh-b", "event:*", at=T0 + dt.timedelta(seconds=1)))
    assert enqueue(catalog, "run.sealed", "run-1", run_id="run-1") == 1
    with session_scope(catalog) as session:
        assert [h.id for h in webhooks.webhooks(session)] == ["wh-a", "wh-b"]
        assert webhooks.webhook(session, "wh-a").subscriptions == ("run.sealed",)
    with session_scope(catalog, write=True) as session:
        assert webhooks.remove_webhook(session, "wh-a").id == "wh-a"
    with session_scope(catalog) as session:
        assert [h.id for h in webhooks.webhooks(session)] == ["wh-b"]
        assert webhooks.claim_due(session, T0, limit=10, hold=HOLD) == []  # its delivery went with it
        with pytest.raises(NotFoundError, match="no webhook 'wh-a'"):
            webhooks.webhook(session, "wh-a")
        with pytest.raises(NotFoundError):
            webhooks.deliveries(session, "wh-a", limit=10)


def test_an_occurrence_goes_once_to_each_webhook_that_subscribes(catalog: sessionmaker[Session]) -> None:
    add(
        catalog,
        hook("wh-kind", "event:intervention"),
        hook("wh-any", "event:*", "robot.silent"),
        hook("wh-sealed", "run.sealed"),
        hook("wh-slack", "event:intervention", body_format="slack"),
    )
    event = {"kind": "intervention", "severity": "warn", "run_id": "run-1", "robot_id": "robot-7", "label": "stop"}
    assert enqueue(catalog, "event:intervention", "ev-1", **event) == 3
    assert enqueue(catalog, "event:intervention", "ev-1", **event) == 0  # the same occurrence: nothing more
    assert enqueue(catalog, "event:hard_brake", "ev-2", kind="hard_brake") == 1  # event:* only
    assert enqueue(catalog, "robot.silent", "run-1@1", run_id="run-1") == 1
    assert enqueue(catalog, "run.sealed", "run-1", run_id="run-1") == 1
    with session_scope(catalog) as session:
        due = {d.id: d for d in webhooks.claim_due(session, T0, limit=100, hold=HOLD)}
    assert sorted(due) == [
        "wh-any:ev-1",
        "wh-any:ev-2",
        "wh-any:run-1@1",
        "wh-kind:ev-1",
        "wh-sealed:run-1",
        "wh-slack:ev-1",
    ]
    body = json.loads(due["wh-kind:ev-1"].body)
    assert body == {**event, "occurrence": "event:intervention", "id": "ev-1", "at": "2026-11-23T08:00:00Z"}
    assert json.loads(due["wh-slack:ev-1"].body) == {"text": "[warn] intervention on run run-1 (robot robot-7): stop"}
    assert all(d.state == PENDING and d.attempts == 0 for d in due.values())


def test_an_occurrence_id_too_long_for_the_column_is_kept_whole_in_the_body(catalog: sessionmaker[Session]) -> None:
    add(catalog, hook("wh-a", "robot.silent"))
    long_id = "r" * 128 + "@2026-11-23T08:00:00.000000Z"
    assert enqueue(catalog, "robot.silent", long_id) == 1
    assert enqueue(catalog, "robot.silent", long_id) == 0
    with session_scope(catalog) as session:
        (due,) = webhooks.claim_due(session, T0, limit=10, hold=HOLD)
    assert len(due.id) <= webhooks.DELIVERY_ID_LENGTH and json.loads(due.body)["id"] == long_id


def test_claimed_deliveries_are_held_then_retried_delivered_or_given_up(catalog: sessionmaker[Session]) -> None:
    add(catalog, hook("wh-a", "event:*"))
    for n in range(3):
        enqueue(catalog, "event:stop", f"ev-{n}")
    with session_scope(catalog, write=True) as session:
        claimed = [d.id for d in webhooks.claim_due(session, T0, limit=2, hold=HOLD)]
    assert claimed == ["wh-a:ev-0", "wh-a:ev-1"]
    with session_scope(catalog, write=True) as session:  # held: another pass takes only the third
        assert [d.id for d in webhooks.claim_due(session, T0, limit=10, hold=HOLD)] == ["wh-a:ev-2"]
    later = T0 + dt.timedelta(minutes=5)
    with session_scope(catalog, write=True) as session:
        webhooks.mark_delivered(session, "wh-a:ev-0", later, 200)
        webhooks.mark_retry(session, "wh-a:ev-1", later + dt.timedelta(seconds=10), 503, "HTTP 503")
        webhooks.mark_failed(session, "wh-a:ev-2", None, "ConnectError: refused")
    with session_scope(catalog) as session:
        page, cursor = webhooks.deliveries(session, "wh-a", limit=10)
    assert cursor is None
    states = {d.id: (d.state, d.attempts, d.last_status, d.last_error) for d in page}
    assert states == {
        "wh-a:ev-0": (DELIVERED, 1, 200, None),
        "wh-a:ev-1": (PENDING, 1, 503, "HTTP 503"),
        "wh-a:ev-2": (FAILED, 1, None, "ConnectError: refused"),
    }
    assert {d.id: d.delivered_at for d in page}["wh-a:ev-0"] == later
    with session_scope(catalog, write=True) as session:
        assert webhooks.claim_due(session, later, limit=10, hold=HOLD) == []  # the retry is not due yet
        (retry,) = webhooks.claim_due(session, later + dt.timedelta(seconds=10), limit=10, hold=HOLD)
    assert retry.id == "wh-a:ev-1"


def test_put_back_deliveries_wait_with_the_one_that_failed(catalog: sessionmaker[Session]) -> None:
    add(catalog, hook("wh-a", "event:*"))
    enqueue(catalog, "event:stop", "ev-1")
    with session_scope(catalog, write=True) as session:
        (claimed,) = webhooks.claim_due(session, T0, limit=10, hold=HOLD)
        webhooks.put_back(session, [claimed.id], T0 + dt.timedelta(minutes=1))
    with session_scope(catalog, write=True) as session:
        assert webhooks.claim_due(session, T0 + HOLD, limit=10, hold=HOLD) == []
        (again,) = webhooks.claim_due(session, T0 + dt.timedelta(minutes=1), limit=10, hold=HOLD)
    assert again.attempts == 0


def test_deliveries_are_paged_newest_first(catalog: sessionmaker[Session]) -> None:
    add(catalog, hook("wh-a", "event:*"))
    for n in range(5):
        with session_scope(catalog, write=True) as session:
            webhooks.enqueue(session, "event:stop", f"ev-{n}", {}, now=T0 + dt.timedelta(seconds=n))
    seen, cursor = [], None
    with session_scope(catalog) as session:
        while True:
            page, cursor = webhooks.deliveries(session, "wh-a", limit=2, cursor=cursor)
            seen.append([d.id.split(":")[1] for d in page])
            if cursor is None:
                break
        with pytest.raises(InvalidArgumentError, match="cursor"):
            webhooks.deliveries(session, "wh-a", limit=2, cursor="not-a-cursor")
    assert seen == [["ev-4", "ev-3"], ["ev-2", "ev-1"], ["ev-0"]]
