"""Webhooks as the REST API and the CLI see them: add one (its URL checked, its secret made, shown
once and kept sealed), list, remove, and the log of its deliveries. `Webhooks` is what the delivery
job and the `robot.silent` pass work with too: the catalog, the clock, the guard and the sealed
secrets of one node."""

from __future__ import annotations

import datetime as dt
import re
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog import webhooks as rows
from catalog.db import session_scope
from catalog.webhooks import ANY_EVENT, BODY_FORMATS, ROBOT_SILENT, RUN_SEALED, WebhookRecord
from core.clock import iso_utc
from core.errors import InvalidArgumentError
from services.auth.keys import load_signing_keys
from services.node import Node
from services.settings import Settings
from services.startup import split_addr
from services.webhooks.guard import HostGuard
from services.webhooks.sealing import SecretBox, new_secret

EVENT_KIND = re.compile(r"event:[A-Za-z0-9._/-]{1,200}")
MAX_SUBSCRIPTIONS = 50
MAX_PAGE = 1000


@dataclass(frozen=True)
class Webhooks:
    """One node's webhooks: where they are kept, when it is, where they may go, their secrets."""

    catalog: sessionmaker[Session]
    clock: Callable[[], dt.datetime]
    guard: HostGuard
    box: SecretBox
    settings: Settings
    default_robot: str


def webhooks_of(node: Node) -> Webhooks:
    """The webhooks of `node`, their secrets sealed with its signing key (the key file in the data dir
    when auth is off, as it is made for signed links)."""
    keys = node.auth.keys
    box = SecretBox(lambda: keys or load_signing_keys(node.settings))
    return Webhooks(node.catalog, node.clock, guard_of(node.settings), box, node.settings, node.default_robot)


def guard_of(settings: Settings) -> HostGuard:
    own = [settings.http_addr, settings.grpc_addr, settings.peer_addr]
    return HostGuard(settings.webhook_hosts, [split_addr(addr)[1] for addr in own])


def parse_subscriptions(on: list[str]) -> tuple[str, ...]:
    """What a webhook is told of, checked: `event:KIND`, `event:*`, `run.sealed`, `robot.silent`."""
    wanted = tuple(dict.fromkeys(s.strip() for s in on))
    if not wanted:
        raise InvalidArgumentError(
            f"a webhook needs at least one --on: event:KIND, {ANY_EVENT}, run.sealed, robot.silent"
        )
    if len(wanted) > MAX_SUBSCRIPTIONS:
        raise InvalidArgumentError(f"a webhook has at most {MAX_SUBSCRIPTIONS} subscriptions")
    for name in wanted:
        if name not in (ANY_EVENT, RUN_SEALED, ROBOT_SILENT) and not EVENT_KIND.fullmatch(name):
            raise InvalidArgumentError(
                f"{name[:100]!r} is nothing a webhook is told of: event:KIND (e.g. event:intervention), "
                f"{ANY_EVENT}, {RUN_SEALED} or {ROBOT_SILENT}"
            )
    return wanted


def add_webhook(hooks: Webhooks, url: str, on: list[str], body_format: str, created_by: str) -> dict[str, Any]:
    """A new webhook, and in this answer only, its signing secret."""
    if body_format not in BODY_FORMATS:
        raise InvalidArgumentError(f"format {body_format[:50]!r}: use {' or '.join(BODY_FORMATS)}")
    subscriptions = parse_subscriptions(on)
    hooks.guard.check(url)
    secret = new_secret()
    record = WebhookRecord(
        id=f"wh-{uuid.uuid4().hex[:12]}",
        url=url,
        subscriptions=subscriptions,
        body_format=body_format,
        secret_sealed=hooks.box.seal(secret),
        created_by=created_by[:256],
        created_at=hooks.clock(),
    )
    with session_scope(hooks.catalog, write=True) as session:
        rows.add_webhook(session, record)
    return {**webhook_answer(record), "secret": secret}


def webhooks_answer(hooks: Webhooks) -> dict[str, Any]:
    with session_scope(hooks.catalog) as session:
        return {"webhooks": [webhook_answer(r) for r in rows.webhooks(session)]}


def remove_webhook(hooks: Webhooks, webhook_id: str) -> dict[str, Any]:
    with session_scope(hooks.catalog, write=True) as session:
        return {**webhook_answer(rows.remove_webhook(session, webhook_id)), "removed": True}


def deliveries_answer(hooks: Webhooks, webhook_id: str, limit: int, cursor: str | None) -> dict[str, Any]:
    """A webhook's deliveries, newest first: each attempt's outcome, a page at a time."""
    if not 1 <= limit <= MAX_PAGE:
        raise InvalidArgumentError(f"limit: 1 to {MAX_PAGE}")
    with session_scope(hooks.catalog) as session:
        page, next_cursor = rows.deliveries(session, webhook_id, limit=limit, cursor=cursor)
    return {"webhook": webhook_id, "deliveries": [delivery_answer(d) for d in page], "next_cursor": next_cursor}


def webhook_answer(record: WebhookRecord) -> dict[str, Any]:
    """A webhook as answers show it: never its secret."""
    return {
        "id": record.id,
        "url": record.url,
        "on": list(record.subscriptions),
        "format": record.body_format,
        "created_by": record.created_by,
        "created_at": iso_utc(record.created_at),
    }


def delivery_answer(delivery: rows.DeliveryRecord) -> dict[str, Any]:
    return {
        "id": delivery.id,
        "occurrence": delivery.occurrence,
        "state": delivery.state,
        "attempts": delivery.attempts,
        "next_at": iso_utc(delivery.next_at) if delivery.state == rows.PENDING else None,
        "last_status": delivery.last_status,
        "last_error": delivery.last_error,
        "created_at": iso_utc(delivery.created_at),
        "delivered_at": iso_utc(delivery.delivered_at),
        "body": delivery.body,
    }
