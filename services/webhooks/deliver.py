"""The delivery job: due deliveries of the outbox POSTed, signed, to their webhooks; each attempt's
status or error recorded; a failed one retried with backoff until `webhook_retry_s` after it was
made, then given up. Re-runnable: run by the schedule every `webhook_interval_s`, it sends what is
due and returns.

A pass is bounded: it takes at most `webhook_batch` deliveries, sends them `webhook_workers` at a
time, each answered within `webhook_timeout_s`, and no redirect is followed. The deliveries of one
webhook go one after the other; when one fails, the rest of that webhook's wait with it, so a dead
endpoint costs one attempt per retry, not one per delivery."""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import logging
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from urllib.parse import urlsplit

import httpx

from catalog import webhooks as rows
from catalog.db import session_scope
from catalog.webhooks import DeliveryRecord, WebhookRecord
from core.backoff import backoff_delay
from core.clock import iso_utc
from core.errors import FleetError
from services import __version__
from services.webhooks.service import Webhooks

log = logging.getLogger(__name__)

FIRST_RETRY_S = 10.0
MAX_RETRY_S = 3600.0
HOLD = dt.timedelta(minutes=10)  # a claimed delivery is left to its pass this long (then due again)
MAX_ERROR = 500
SIGNATURE_HEADER, DELIVERY_HEADER, OCCURRENCE_HEADER = "X-Fleet-Signature", "X-Fleet-Delivery", "X-Fleet-Occurrence"


@dataclass(frozen=True)
class Outcome:
    """One attempt: the endpoint's status (None when there was no answer) and what went wrong."""

    status: int | None
    error: str | None

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass(frozen=True)
class PassReport:
    delivered: int = 0
    retrying: int = 0
    failed: int = 0
    waiting: int = 0  # not attempted: their webhook had just failed


def signature(secret: str, body: bytes) -> str:
    """The `X-Fleet-Signature` of `body`: `sha256=` and the hex HMAC-SHA256 of it under the secret."""
    return "sha256=" + hmac.new(secret.encode(), body, hashlib.sha256).hexdigest()


def deliver_due(hooks: Webhooks, *, transport: httpx.BaseTransport | None = None) -> PassReport:
    """Send what is due now; what happened to each delivery taken."""
    settings = hooks.settings
    with session_scope(hooks.catalog, write=True) as session:
        due = rows.claim_due(session, hooks.clock(), limit=settings.webhook_batch, hold=HOLD)
        targets = {hook.id: hook for hook in rows.webhooks(session)} if due else {}
    if not due:
        return PassReport()
    by_webhook: dict[str, list[DeliveryRecord]] = defaultdict(list)
    for delivery in due:
        by_webhook[delivery.webhook_id].append(delivery)
    with (
        httpx.Client(
            timeout=settings.webhook_timeout_s, follow_redirects=False, trust_env=False, transport=transport
        ) as client,
        ThreadPoolExecutor(settings.webhook_workers, thread_name_prefix="webhooks") as pool,
    ):
        reports = list(
            pool.map(lambda item: _deliver_in_order(hooks, client, targets.get(item[0]), item[1]), by_webhook.items())
        )
    return PassReport(*(sum(getattr(r, f) for r in reports) for f in ("delivered", "retrying", "failed", "waiting")))


def _deliver_in_order(
    hooks: Webhooks, client: httpx.Client, hook: WebhookRecord | None, deliveries: list[DeliveryRecord]
) -> PassReport:
    """One webhook's deliveries, oldest first, until one fails: the others then wait with it."""
    if hook is None:  # removed meanwhile, and its deliveries with it
        return PassReport()
    delivered = 0
    for n, delivery in enumerate(deliveries):
        outcome = attempt(hooks, client, hook, delivery)
        if outcome.ok:
            delivered += 1
            continue
        again = _failed(hooks, hook, delivery, outcome)
        rest = [d.id for d in deliveries[n + 1 :]]
        with session_scope(hooks.catalog, write=True) as session:
            rows.put_back(session, rest, again or hooks.clock() + dt.timedelta(seconds=FIRST_RETRY_S))
        return PassReport(delivered, int(again is not None), int(again is None), len(rest))
    return PassReport(delivered)


def attempt(hooks: Webhooks, client: httpx.Client, hook: WebhookRecord, delivery: DeliveryRecord) -> Outcome:
    """Send one delivery and record the outcome if it was delivered (failures: `_failed`)."""
    outcome = _send(hooks, client, hook, delivery)
    if outcome.ok:
        assert outcome.status is not None
        with session_scope(hooks.catalog, write=True) as session:
            rows.mark_delivered(session, delivery.id, hooks.clock(), outcome.status)
    return outcome


def _send(hooks: Webhooks, client: httpx.Client, hook: WebhookRecord, delivery: DeliveryRecord) -> Outcome:
    try:
        target = hooks.guard.check(hook.url)  # the policy and the name's addresses as they are now
        secret = hooks.box.open(hook.secret_sealed)
    except FleetError as exc:
        return Outcome(None, f"refused: {exc.message}"[:MAX_ERROR])
    body = delivery.body.encode()
    headers = {
        "Host": target.host_header,
        "Content-Type": "application/json",
        "User-Agent": f"fleet-telemetry/{__version__}",
        SIGNATURE_HEADER: signature(secret, body),
        DELIVERY_HEADER: delivery.id,
        OCCURRENCE_HEADER: delivery.occurrence,
    }
    try:
        # To the address checked, by its name for TLS; the answer's body is never read.
        with client.stream(
            "POST", target.connect_url, content=body, headers=headers, extensions={"sni_hostname": target.host}
        ) as response:
            status = response.status_code
    except httpx.HTTPError as exc:
        return Outcome(None, f"{type(exc).__name__}: {exc}"[:MAX_ERROR] if str(exc) else type(exc).__name__)
    if 200 <= status < 300:
        return Outcome(status, None)
    if 300 <= status < 400:
        return Outcome(status, f"HTTP {status}: a redirect, not followed (give the webhook its final URL)")
    return Outcome(status, f"HTTP {status}")


def _failed(hooks: Webhooks, hook: WebhookRecord, delivery: DeliveryRecord, outcome: Outcome) -> dt.datetime | None:
    """Record a failed attempt: when it is tried again, or None when given up (past the retry window)."""
    now = hooks.clock()
    assert outcome.error is not None
    deadline = delivery.created_at + dt.timedelta(seconds=hooks.settings.webhook_retry_s)
    host = urlsplit(hook.url).netloc  # the host only: a URL's path may be a secret (Slack's are)
    with session_scope(hooks.catalog, write=True) as session:
        if now >= deadline:
            rows.mark_failed(session, delivery.id, outcome.status, outcome.error)
            log.warning(
                "webhook %s: delivery %s to %s given up after %d attempts: %s",
                hook.id,
                delivery.id,
                host,
                delivery.attempts + 1,
                outcome.error,
            )
            return None
        delay = backoff_delay(delivery.attempts + 1, first=FIRST_RETRY_S, cap=MAX_RETRY_S)
        again = min(now + dt.timedelta(seconds=delay), deadline)
        rows.mark_retry(session, delivery.id, again, outcome.status, outcome.error)
    log.info(
        "webhook %s: delivery %s to %s failed (%s), again at %s",
        hook.id,
        delivery.id,
        host,
        outcome.error,
        iso_utc(again),
    )
    return again
