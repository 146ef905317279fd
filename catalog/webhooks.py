"""Catalog reads and writes of webhooks and their outbox of deliveries.

Writers of occurrences (events made, runs sealed, robots gone silent) call `enqueue` inside their
own transaction: one pending delivery per webhook that subscribes to the occurrence, at most once
per webhook and occurrence (the delivery's id is the webhook's and the occurrence's). The delivery
job claims due deliveries (`claim_due`), sends them, and records each attempt."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import insert
from sqlalchemy.orm import Session

from catalog.models import Webhook, WebhookDelivery
from core.clock import aware, iso_utc, utcnow
from core.cursors import decode_cursor, encode_cursor
from core.errors import NotFoundError

PENDING, DELIVERED, FAILED = "pending", "delivered", "failed"
JSON, SLACK = "json", "slack"
BODY_FORMATS = (JSON, SLACK)
RUN_SEALED, ROBOT_SILENT, EVENT_PREFIX = "run.sealed", "robot.silent", "event:"
ANY_EVENT = "event:*"
DELIVERY_ID_LENGTH = 64  # the column's width


@dataclass(frozen=True)
class WebhookRecord:
    id: str
    url: str
    subscriptions: tuple[str, ...]
    body_format: str
    secret_sealed: str  # never leaves the depot: answers are made by `webhook_answer`
    created_by: str
    created_at: dt.datetime


@dataclass(frozen=True)
class DeliveryRecord:
    id: str
    webhook_id: str
    occurrence: str
    body: str
    state: str
    attempts: int
    next_at: dt.datetime
    last_status: int | None
    last_error: str | None
    created_at: dt.datetime
    delivered_at: dt.datetime | None


# --- webhooks ----------------------------------------------------------------------------------------


def add_webhook(session: Session, record: WebhookRecord) -> None:
    session.add(
        Webhook(
            id=record.id,
            url=record.url,
            subscriptions=json.dumps(list(record.subscriptions)),
            body_format=record.body_format,
            secret_sealed=record.secret_sealed,
            created_by=record.created_by,
            created_at=record.created_at,
        )
    )


def webhooks(session: Session) -> list[WebhookRecord]:
    """Every webhook, oldest first."""
    return [_webhook(row) for row in session.scalars(sa.select(Webhook).order_by(Webhook.created_at, Webhook.id))]


def webhook(session: Session, webhook_id: str) -> WebhookRecord:
    row = session.get(Webhook, webhook_id)
    if row is None:
        raise NotFoundError(f"no webhook {webhook_id!r}: `fleet webhooks ls` lists them")
    return _webhook(row)


def remove_webhook(session: Session, webhook_id: str) -> WebhookRecord:
    """Remove a webhook and its deliveries (those pending are never sent)."""
    record = webhook(session, webhook_id)
    session.execute(sa.delete(WebhookDelivery).where(WebhookDelivery.webhook_id == webhook_id))
    session.execute(sa.delete(Webhook).where(Webhook.id == webhook_id))
    return record


def subscribes(subscriptions: tuple[str, ...], occurrence: str) -> bool:
    """Whether a webhook with these subscriptions is told of `occurrence` (`event:KIND`,
    `run.sealed`, `robot.silent`): by its very name, or any event by `event:*`."""
    return occurrence in subscriptions or (occurrence.startswith(EVENT_PREFIX) and ANY_EVENT in subscriptions)


def _webhook(row: Webhook) -> WebhookRecord:
    return WebhookRecord(
        id=row.id,
        url=row.url,
        subscriptions=tuple(json.loads(row.subscriptions)),
        body_format=row.body_format,
        secret_sealed=row.secret_sealed,
        created_by=row.created_by,
        created_at=aware(row.created_at),
    )


# --- the outbox ----------------------------------------------------------------------------------------


def delivery_id(webhook_id: str, occurrence_id: str) -> str:
    """`WEBHOOK:OCCURRENCE`; an occurrence id too long for the column is replaced by its digest,
    which is as unique and as stable."""
    whole = f"{webhook_id}:{occurrence_id}"
    if len(whole) <= DELIVERY_ID_LENGTH:
        return whole
    return f"{webhook_id}:h-{hashlib.sha256(occurrence_id.encode()).hexdigest()[:40]}"


def enqueue(
    session: Session,
    occurrence: str,
    occurrence_id: str,
    payload: dict[str, Any],
    *,
    now: dt.datetime | None = None,
    hooks: list[WebhookRecord] | None = None,
) -> int:
    """One pending delivery of `occurrence` (its id `occurrence_id`, what it is about `payload`) to
    each webhook subscribed to it, in the caller's transaction; how many were added. The same
    occurrence enqueued again adds nothing. `hooks`: the webhooks as the caller read them in this
    transaction (one read for many occurrences)."""
    now = now or utcnow()
    listed = webhooks(session) if hooks is None else hooks
    targets = [hook for hook in listed if subscribes(hook.subscriptions, occurrence)]
    if not targets:
        return 0
    ids = {hook.id: delivery_id(hook.id, occurrence_id) for hook in targets}
    there = set(session.scalars(sa.select(WebhookDelivery.id).where(WebhookDelivery.id.in_(ids.values()))))
    document = {**payload, "occurrence": occurrence, "id": occurrence_id, "at": payload.get("at") or iso_utc(now)}
    added = 0
    for hook in targets:
        if ids[hook.id] in there:
            continue
        row = dict(
            id=ids[hook.id],
            webhook_id=hook.id,
            occurrence=occurrence,
            body=body_for(hook.body_format, document),
            state=PENDING,
            attempts=0,
            next_at=now,
            created_at=now,
        )
        # The check above keeps a repeat from trying; the clause keeps a race between two writers
        # from failing either one's transaction.
        inserted = insert(WebhookDelivery).values(**row).on_conflict_do_nothing().returning(WebhookDelivery.id)
        added += len(session.execute(inserted).all())  # (DuckDB gives no row counts)
    return added


def body_for(body_format: str, document: dict[str, Any]) -> str:
    """The body sent to a webhook, as stored (what it is signed over): the JSON document, or for
    `slack` a Slack-compatible message `{"text": ...}`."""
    if body_format == SLACK:
        document = {"text": slack_text(document)}
    return json.dumps(document, separators=(",", ":"), default=_plain)


def slack_text(document: dict[str, Any]) -> str:
    """One line saying what happened, for people reading a chat channel."""
    occurrence, get = str(document.get("occurrence")), document.get
    if occurrence.startswith(EVENT_PREFIX):
        label = f": {get('label')}" if get("label") else ""
        return f"[{get('severity', 'info')}] {get('kind')} on run {get('run_id')} (robot {get('robot_id')}){label}"
    if occurrence == RUN_SEALED:
        return f"run {get('run_id')} of robot {get('robot_id')} sealed"
    if occurrence == ROBOT_SILENT:
        return f"robot {get('robot_id')} silent since {get('last_data_at')} (run {get('run_id')})"
    return f"{occurrence} {get('id')}"


def _plain(value: Any) -> Any:
    if isinstance(value, dt.datetime):
        return iso_utc(value)
    return str(value)


def claim_due(session: Session, now: dt.datetime, *, limit: int, hold: dt.timedelta) -> list[DeliveryRecord]:
    """Up to `limit` pending deliveries due by `now`, oldest due first, each held for `hold` (its
    `next_at` moved on) so that no other process sends it meanwhile: a delivery whose `next_at`
    another process changed first is left to that one."""
    query = (
        sa.select(WebhookDelivery)
        .where(WebhookDelivery.state == PENDING, WebhookDelivery.next_at <= now)
        .order_by(WebhookDelivery.next_at, WebhookDelivery.id)
        .limit(limit)
    )
    claimed = []
    for row in list(session.scalars(query)):
        record = _delivery(row)
        took = session.execute(
            sa.update(WebhookDelivery)
            .where(
                WebhookDelivery.id == row.id,
                WebhookDelivery.state == PENDING,
                WebhookDelivery.next_at == record.next_at,
            )
            .values(next_at=now + hold)
            .returning(WebhookDelivery.id)
            .execution_options(synchronize_session=False)
        )
        if took.first() is not None:  # (DuckDB gives no row counts)
            claimed.append(record)
    return claimed


def mark_delivered(session: Session, delivery: str, now: dt.datetime, status: int) -> None:
    _attempted(session, delivery, state=DELIVERED, last_status=status, last_error=None, delivered_at=now)


def mark_retry(session: Session, delivery: str, next_at: dt.datetime, status: int | None, error: str) -> None:
    _attempted(session, delivery, state=PENDING, next_at=next_at, last_status=status, last_error=error)


def mark_failed(session: Session, delivery: str, status: int | None, error: str) -> None:
    """Given up: no more attempts."""
    _attempted(session, delivery, state=FAILED, last_status=status, last_error=error)


def put_back(session: Session, deliveries: list[str], next_at: dt.datetime) -> None:
    """Claimed deliveries not attempted (their endpoint just failed): due again at `next_at`."""
    if deliveries:
        session.execute(
            sa.update(WebhookDelivery)
            .where(WebhookDelivery.id.in_(deliveries), WebhookDelivery.state == PENDING)
            .values(next_at=next_at)
            .execution_options(synchronize_session=False)
        )


def _attempted(session: Session, delivery: str, **values: Any) -> None:
    session.execute(
        sa.update(WebhookDelivery)
        .where(WebhookDelivery.id == delivery)
        .values(attempts=WebhookDelivery.attempts + 1, **values)
        .execution_options(synchronize_session=False)
    )


def deliveries(
    session: Session, webhook_id: str, *, limit: int, cursor: str | None = None
) -> tuple[list[DeliveryRecord], str | None]:
    """A webhook's deliveries, newest first, a page of `limit` after `cursor`, and the cursor of the
    next page (None at the end)."""
    webhook(session, webhook_id)  # 404 for a webhook that is not there
    query = sa.select(WebhookDelivery).where(WebhookDelivery.webhook_id == webhook_id)
    if cursor:
        created, last = decode_cursor(cursor)
        query = query.where(
            sa.or_(
                WebhookDelivery.created_at < created,
                sa.and_(WebhookDelivery.created_at == created, WebhookDelivery.id < last),
            )
        )
    query = query.order_by(WebhookDelivery.created_at.desc(), WebhookDelivery.id.desc()).limit(limit + 1)
    page = [_delivery(row) for row in session.scalars(query)]
    more = len(page) > limit
    page = page[:limit]
    return page, encode_cursor(page[-1].created_at, page[-1].id) if more else None


def _delivery(row: WebhookDelivery) -> DeliveryRecord:
    return DeliveryRecord(
        id=row.id,
        webhook_id=row.webhook_id,
        occurrence=row.occurrence,
        body=row.body,
        state=row.state,
        attempts=row.attempts,
        next_at=aware(row.next_at),
        last_status=row.last_status,
        last_error=row.last_error,
        created_at=aware(row.created_at),
        delivered_at=aware(row.delivered_at) if row.delivered_at is not None else None,
    )
