"""Feeding an ingest service the way its handlers do: `prepare` then `accept` for each message, and
an upload closed with `finish_upload` (the catalog brought up to date before it is answered)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterable

from services.ingest.service import IngestReport, IngestService, Source
from services.rrd.messages import Event


async def _feed(service: IngestService, source: Source, events: Iterable[Event]) -> None:
    for event in events:
        await service.prepare(source, event)
        service.accept(source, event)


def feed(service: IngestService, source: Source, events: Iterable[Event]) -> None:
    """File `events` into an open source (raises what the handler would turn into an error answer)."""
    asyncio.run(_feed(service, source, events))


def upload(service: IngestService, events: Iterable[Event]) -> IngestReport:
    """One upload of `events`, closed (and the catalog updated) even if a message is refused."""
    source = service.open_source(live=False)
    try:
        feed(service, source, events)
    finally:
        report = asyncio.run(service.finish_upload(source))
    return report
