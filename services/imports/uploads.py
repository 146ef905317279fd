"""Messages of an upload filed through the ingest service, the same way for an `.rrd` body as it
arrives and for the recording an MCAP file was converted to: each message prepared (who files its
run), relayed whole to the node that owns the run if that is another, else accepted here.

The answer is the ingest report, or a refusal naming the byte offset where the body turned bad (the
chunks before it are kept). A client gone mid-body keeps what came whole and closes its runs.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

from starlette.requests import ClientDisconnect

from core.errors import FleetError
from services.auth.tokens import Auth
from services.cluster.relay import request_of
from services.ingest.routing import relay_source
from services.ingest.service import IngestService
from services.ingest.source import Source
from services.rrd.messages import Event

log = logging.getLogger(__name__)
CLIENT_GONE = 499  # nginx's "client closed request": nobody reads it


@dataclass(frozen=True)
class Filed:
    """How an upload ended: the HTTP status and the JSON answer (an ingest report, or an error with
    `accepted`, what was kept before it)."""

    status: int
    body: dict[str, Any]
    headers: dict[str, str]

    @property
    def report(self) -> dict[str, Any]:
        return self.body.get("accepted", self.body) if self.status >= 400 else self.body


async def file_events(
    service: IngestService, auth: Auth, source: Source, authorization: str | None, events: AsyncIterator[Event]
) -> Filed:
    """File every event of an upload into `source`, and close it."""
    try:
        async for event in events:
            await service.prepare(source, event)
            if source.relay_to is not None:
                answer = await _relayed(service, auth, source, authorization, event, events)
                if answer is not None:
                    service.close_source(source)
                    return Filed(200, answer, {})
            service.accept(source, event)
    except FleetError as exc:
        report = await service.finish_upload(source)
        body = {**exc.to_dict(), "offset": getattr(exc, "offset", None), "accepted": report.to_dict()}
        return Filed(exc.http_status(), body, exc.headers())
    except ClientDisconnect:
        return await _client_gone(service, source)
    return Filed(200, (await service.finish_upload(source)).to_dict(), {})


async def _client_gone(service: IngestService, source: Source) -> Filed:
    """The client went away mid-body: what came whole is kept (sending the file again completes it,
    chunks held being skipped) and its runs are closed, as at the end of any upload. One log line,
    no traceback: a dropped connection is the client's doing, not a fault of the depot."""
    report = await service.finish_upload(source)
    log.info(
        "upload ended by its client mid-body: kept %d new chunks of runs %s; sending it again completes them",
        report.chunks_new,
        ", ".join(report.runs) or "(none)",
    )
    return Filed(CLIENT_GONE, {"error": {"code": "CLIENT_GONE"}, "accepted": report.to_dict()}, {})


async def _relayed(
    service: IngestService,
    auth: Auth,
    source: Source,
    authorization: str | None,
    first: Event,
    rest: AsyncIterator[Event],
) -> dict[str, Any] | None:
    """The rest of the upload sent to the node that owns its run, and that node's answer; None if
    this node took the run over meanwhile (it files the upload itself)."""

    async def requests() -> AsyncIterator[bytes]:
        async for event in rest:
            if (message := request_of(event)) is not None:
                yield message

    metadata = [("authorization", authorization)] if authorization else []
    return await relay_source(service, auth, source, metadata, [first], requests())
