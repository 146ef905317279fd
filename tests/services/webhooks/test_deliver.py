"""The delivery job against a real endpoint on loopback: each occurrence delivered once, signed;
failures retried with backoff, then given up a day later (a clock moved by hand: no waiting); a dead
endpoint costs one attempt per pass; no redirect followed; the guard checked again at delivery."""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import hmac
import json
import logging
import socket
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import webhooks as rows
from catalog.db import session_scope
from services.webhooks import service
from services.webhooks.deliver import PassReport, deliver_due
from services.webhooks.guard import HostGuard
from services.webhooks.service import Webhooks
from tests.services.retention.conftest import Clock
from tests.services.webhooks.conftest import Receiver

EVENT = {"kind": "intervention", "severity": "warn", "run_id": "run-1", "robot_id": "robot-7", "label": "took over"}


def enqueue(hooks: Webhooks, occurrence: str, occurrence_id: str, payload: dict[str, Any]) -> int:
    with session_scope(hooks.catalog, write=True) as session:
        return rows.enqueue(session, occurrence, occurrence_id, payload, now=hooks.clock())


def deliveries(hooks: Webhooks, webhook_id: str) -> list[dict[str, Any]]:
    found: list[dict[str, Any]] = service.deliveries_answer(hooks, webhook_id, 100, None)["deliveries"]
    return found


def signed(secret: str, body: bytes) -> str:
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


def test_each_occurrence_reaches_the_receiver_once_with_a_valid_signature(hooks: Webhooks, receiver: Receiver):
    added = service.add_webhook(hooks, receiver.url, ["event:intervention", "run.sealed"], "json", "alice")
    secret = added["secret"]
    assert enqueue(hooks, "event:intervention", "ev-1", EVENT) == 1
    assert enqueue(hooks, "event:intervention", "ev-1", EVENT) == 0  # the same event again: nothing more
    assert enqueue(hooks, "event:hard_brake", "ev-2", {**EVENT, "kind": "hard_brake"}) == 0  # not subscribed
    assert deliver_due(hooks) == PassReport(delivered=1)
    assert deliver_due(hooks) == PassReport()  # delivered already: nothing sent again
    (got,) = receiver.got
    assert got.path == "/hook"
    assert got.headers["x-fleet-signature"] == signed(secret, got.body)
    assert got.headers["x-fleet-delivery"] == f"{added['id']}:ev-1"
    assert got.headers["content-type"] == "application/json"
    assert json.loads(got.body) == {**EVENT, "occurrence": "event:intervention", "id": "ev-1", "at": _iso(hooks)}
    (logged,) = deliveries(hooks, added["id"])
    assert (logged["state"], logged["attempts"], logged["last_status"], logged["last_error"]) == (
        "delivered",
        1,
        200,
        None,
    )
    assert logged["body"] == got.body.decode()


def test_a_failing_receiver_is_tried_again_later_then_delivered(hooks: Webhooks, receiver: Receiver, clock: Clock):
    added = service.add_webhook(hooks, receiver.url, ["run.sealed"], "json", "alice")
    enqueue(hooks, "run.sealed", "run-1", {"run_id": "run-1", "robot_id": "robot-7"})
    receiver.answers = [500]
    assert deliver_due(hooks) == PassReport(retrying=1)
    (first,) = deliveries(hooks, added["id"])
    assert (first["state"], first["attempts"], first["last_status"], first["last_error"]) == (
        "pending",
        1,
        500,
        "HTTP 500",
    )
    assert first["next_at"] == _iso(hooks, seconds=10)  # the backoff's first step
    assert deliver_due(hooks) == PassReport()  # not due yet
    assert len(receiver.got) == 1
    clock.advance(seconds=10)
    assert deliver_due(hooks) == PassReport(delivered=1)
    assert [g.body for g in receiver.got] == [receiver.got[0].body] * 2  # the same body, signed the same
    (done,) = deliveries(hooks, added["id"])
    assert (done["state"], done["attempts"], done["last_status"], done["last_error"]) == ("delivered", 2, 200, None)


def test_a_delivery_is_given_up_a_day_after_it_was_made(hooks: Webhooks, receiver: Receiver, clock: Clock):
    added = service.add_webhook(hooks, receiver.url, ["run.sealed"], "json", "alice")
    enqueue(hooks, "run.sealed", "run-1", {"run_id": "run-1"})
    receiver.answers = [503] * 100
    delays = []
    for _ in range(5):  # the waits double
        before = clock()
        assert deliver_due(hooks) == PassReport(retrying=1)
        clock.now = dt.datetime.fromisoformat(deliveries(hooks, added["id"])[0]["next_at"])
        delays.append((clock() - before).total_seconds())
    assert delays == [10, 20, 40, 80, 160]
    clock.advance(hours=24)
    assert deliver_due(hooks) == PassReport(failed=1)
    (gone,) = deliveries(hooks, added["id"])
    assert (gone["state"], gone["attempts"], gone["last_status"], gone["next_at"]) == ("failed", 6, 503, None)
    clock.advance(hours=1)
    assert deliver_due(hooks) == PassReport()  # never again
    assert len(receiver.got) == 6


def test_a_dead_endpoint_costs_one_attempt_per_pass(hooks: Webhooks, receiver: Receiver, clock: Clock):
    dead_port = _free_port()
    hooks = dataclasses.replace(hooks, guard=HostGuard([f"127.0.0.1:{dead_port}", f"127.0.0.1:{receiver.port}"], []))
    dead = service.add_webhook(hooks, f"http://127.0.0.1:{dead_port}/", ["event:*"], "json", "alice")
    alive = service.add_webhook(hooks, receiver.url, ["event:*"], "json", "alice")
    for n in range(3):
        enqueue(hooks, "event:stop", f"ev-{n}", {"kind": "stop"})
    assert deliver_due(hooks) == PassReport(delivered=3, retrying=1, waiting=2)
    assert len(receiver.got) == 3  # the live endpoint is not held up by the dead one
    tried = {d["id"]: (d["attempts"], d["next_at"]) for d in deliveries(hooks, dead["id"])}
    again = _iso(hooks, seconds=10)
    assert tried == {
        f"{dead['id']}:ev-0": (1, again),
        f"{dead['id']}:ev-1": (0, again),
        f"{dead['id']}:ev-2": (0, again),
    }
    assert "ConnectError" in deliveries(hooks, dead["id"])[-1]["last_error"]
    assert all(d["state"] == "delivered" for d in deliveries(hooks, alive["id"]))


def test_a_redirect_is_not_followed(hooks: Webhooks, receiver: Receiver):
    added = service.add_webhook(hooks, receiver.url, ["run.sealed"], "json", "alice")
    enqueue(hooks, "run.sealed", "run-1", {"run_id": "run-1"})
    receiver.answers = [302]
    assert deliver_due(hooks) == PassReport(retrying=1)
    (logged,) = deliveries(hooks, added["id"])
    assert logged["last_status"] == 302 and "redirect, not followed" in logged["last_error"]
    assert len(receiver.got) == 1


def test_a_slack_body_is_a_text_message_signed_the_same_way(hooks: Webhooks, receiver: Receiver):
    added = service.add_webhook(hooks, receiver.url, ["event:*"], "slack", "alice")
    enqueue(hooks, "event:intervention", "ev-1", EVENT)
    deliver_due(hooks)
    (got,) = receiver.got
    assert json.loads(got.body) == {"text": "[warn] intervention on run run-1 (robot robot-7): took over"}
    assert got.headers["x-fleet-signature"] == signed(added["secret"], got.body)


def test_the_guard_is_asked_again_at_each_delivery(hooks: Webhooks, receiver: Receiver):
    """A name that resolved to the receiver when the webhook was added and to a metadata address
    later is refused then: the delivery connects only to an address it checked."""
    answers = {"hooks.example": ["127.0.0.1"]}
    named = HostGuard(["hooks.example"], [], resolver=lambda host, port: answers[host])
    hooks = dataclasses.replace(hooks, guard=named)
    added = service.add_webhook(hooks, f"http://hooks.example:{receiver.port}/named", ["event:*"], "json", "alice")
    enqueue(hooks, "event:stop", "ev-1", {"kind": "stop"})
    assert deliver_due(hooks) == PassReport(delivered=1)
    assert receiver.got[0].headers["host"] == f"hooks.example:{receiver.port}"  # by its name, to the address checked
    answers["hooks.example"] = ["127.0.0.1", "169.254.169.254"]
    enqueue(hooks, "event:stop", "ev-2", {"kind": "stop"})
    assert deliver_due(hooks) == PassReport(retrying=1)
    assert len(receiver.got) == 1
    refused = next(d for d in deliveries(hooks, added["id"]) if d["id"].endswith("ev-2"))
    assert refused["last_error"].startswith("refused: ") and "169.254.169.254" in refused["last_error"]
    emptied = dataclasses.replace(hooks, guard=HostGuard([], []))  # the admin emptied the list since
    enqueue(emptied, "event:stop", "ev-3", {"kind": "stop"})
    assert deliver_due(emptied) == PassReport(retrying=1)
    assert len(receiver.got) == 1
    refused = next(d for d in deliveries(hooks, added["id"]) if d["id"].endswith("ev-3"))
    assert "FLEET_WEBHOOK_HOSTS" in refused["last_error"]


def test_the_secret_is_never_in_answers_logs_or_the_catalog_in_clear(
    hooks: Webhooks, receiver: Receiver, catalog: sessionmaker[Session], caplog: pytest.LogCaptureFixture
):
    caplog.set_level(logging.DEBUG)
    added = service.add_webhook(hooks, receiver.url, ["event:*"], "json", "alice")
    secret = added["secret"]
    assert secret.startswith("whsec_") and len(secret) > 40
    enqueue(hooks, "event:stop", "ev-1", {"kind": "stop"})
    receiver.answers = [500]
    deliver_due(hooks)
    answers = json.dumps([service.webhooks_answer(hooks), deliveries(hooks, added["id"])])
    assert added["id"] in answers and secret not in answers
    assert secret not in caplog.text and added["id"] in caplog.text  # the failure was logged, without it
    with session_scope(catalog) as session:
        (record,) = rows.webhooks(session)
    assert secret not in record.secret_sealed and hooks.box.open(record.secret_sealed) == secret


def _iso(hooks: Webhooks, **later: float) -> str:
    return (hooks.clock() + dt.timedelta(**later)).isoformat().replace("+00:00", "Z")


def _free_port() -> int:
    """A loopback port nothing listens on (bound and closed at once: connections are refused)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port
