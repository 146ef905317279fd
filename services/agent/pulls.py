"""Pulls: an engineer asks the depot for data the live rules kept on the robot (a run, or a window
and entity set of it); the depot queues the request for the robot's agent, which polls for it,
picks exactly those chunks from its spool (the window's chunks, the static ones and, per entity and
component, the newest before the window's start, as a download would), and sends the ones the depot
lacks, each once, behind live data and backfill.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from core.errors import FleetError
from services.hot.index import HotEntry, read_hot_index
from services.rrd.chunk_index import CHUNK
from services.runs.download import EntityFilter, TimeWindow, parse_time_value
from services.runs.latest_at import ChunkEntry, select_chunks

log = logging.getLogger("fleet.agent")


@dataclass(frozen=True)
class PullSpec:
    """What a pull asks for, as the depot queued it."""

    pull_id: str
    run_id: str
    include: list[str]
    exclude: list[str]
    timeline: str | None
    start: str | None
    end: str | None
    origin: str = "person"  # person | trigger (the depot's live rules found the event)
    priority: str | None = None  # a trigger's: high | normal
    event_id: str | None = None  # the event whose window this is

    @classmethod
    def of(cls, pull: dict[str, Any]) -> PullSpec:
        return cls(
            str(pull["id"]),
            str(pull["run"] if "run" in pull else pull["run_id"]),
            list(pull.get("include") or []),
            list(pull.get("exclude") or []),
            pull.get("timeline"),
            pull.get("start"),
            pull.get("end"),
            str(pull.get("origin") or "person"),
            pull.get("priority"),
            pull.get("event_id"),
        )


class PullRefused(FleetError):
    """The pull cannot be served (an unknown timeline, a value it cannot read): failed, with why."""


def select_pull(spec: PullSpec, run_file: Path, size: int, timeline_types: dict[str, str]) -> list[HotEntry]:
    """The recording chunks of the spooled run that the pull asks for, in file order."""
    entities = EntityFilter(spec.include, spec.exclude)
    entries = [
        e
        for e in read_hot_index(run_file, size).entries
        if e.kind == CHUNK and e.meta is not None and e.store_kind == "recording" and entities(e.meta.entity_path)
    ]
    window = _window(spec, timeline_types)
    if window is None:
        return entries
    chosen = [ChunkEntry.of_meta(e.meta, True, window.timeline) for e in entries if e.meta is not None]
    keep, _ = select_chunks(chosen, window.bounds, True, lambda unknown: unknown)
    return [e for e in entries if e.meta is not None and e.meta.chunk_id in keep]


def _window(spec: PullSpec, timeline_types: dict[str, str]) -> TimeWindow | None:
    if spec.timeline is None:
        if spec.start is not None or spec.end is not None:
            raise PullRefused("start and end need a timeline")
        return None
    kind = timeline_types.get(spec.timeline)
    if kind is None:
        known = ", ".join(sorted(timeline_types)) or "none"
        raise PullRefused(f"run {spec.run_id} has no timeline {spec.timeline!r} on the robot (it has: {known})")
    try:
        start = parse_time_value("start", kind, spec.start) if spec.start is not None else None
        end = parse_time_value("end", kind, spec.end) if spec.end is not None else None
    except FleetError as exc:
        raise PullRefused(str(exc)) from exc
    return TimeWindow(spec.timeline, start, end)
