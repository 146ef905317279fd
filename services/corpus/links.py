"""Events as answers: each with its times as people read them and a link that opens its window of
the run in the Rerun viewer (signed with the asker's grant when auth is on, as `fleet view` links
are)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from catalog.models import Event
from core.clock import iso_utc
from core.timefmt import timestamp
from services.auth.scopes import Principal
from services.auth.tokens import Auth

# How much of the run around an event its link shows: a few seconds either side on timestamp and
# duration timelines (in ns). A sequence tick has no length in seconds: a sequence event's link
# shows its range as is, the scene at its start included (the recording's latest-at).
PAD_NS = 5_000_000_000
TIME_MIN, TIME_MAX = -(2**63), 2**63 - 1


@dataclass(frozen=True)
class Viewer:
    """What an event's viewer link is made with: the depot's auth (signing), who asked (a signed
    link reads with their grant, and ends with it), the depot's public base URL, and how long the
    link lasts."""

    auth: Auth
    principal: Principal
    base_url: str
    ttl: dt.timedelta

    def window_url(self, run_id: str, timeline: str, start: int, end: int) -> str:
        params = [("timeline", timeline), ("start", str(start)), ("end", str(end))]
        expires_at = self.auth.clock().replace(microsecond=0) + self.ttl
        return self.base_url.rstrip("/") + self.auth.sign_link(self.principal, run_id, params, expires_at)


def padded(timeline_type: str, start: int, end: int) -> tuple[int, int]:
    """The event's range widened by PAD_NS on time timelines, kept within signed 64 bits."""
    pad = 0 if timeline_type == "sequence" else PAD_NS
    return max(TIME_MIN, start - pad), min(TIME_MAX, end + pad)


def event_answer(event: Event, viewer: Viewer, data: dict[str, Any] | None = None) -> dict[str, Any]:
    """An event as every route answers it. `start`/`end` are the raw timeline values (ns since the
    epoch on a timestamp timeline); `start_iso`/`end_iso` the same as ISO-8601 on timestamp
    timelines (None on others). `data`: where its window's data is (`catalog.edge.event_data`:
    None when no pull asked for it)."""
    on_clock = event.timeline_type == "timestamp"
    window = padded(event.timeline_type, event.range_start, event.range_end)
    return {
        "id": event.id,
        "run_id": event.run_id,
        "robot_id": event.robot_id,
        "kind": event.kind,
        "severity": event.severity,
        "timeline": event.timeline,
        "timeline_type": event.timeline_type,
        "start": event.range_start,
        "end": event.range_end,
        "start_iso": timestamp(event.range_start) if on_clock else None,
        "end_iso": timestamp(event.range_end) if on_clock else None,
        "source": event.source,
        "origin": event.origin,
        "rules_version": event.rules_version,
        "label": event.label,
        "note": event.note,
        "created_at": iso_utc(event.created_at),
        "viewer_url": viewer.window_url(event.run_id, event.timeline, *window),
        "data": data,
    }
