"""Recordings for the rules' tests, logged with the real rerun-sdk in this process (one
`RecordingStream` each, saved to a file), and read back as the depot reads a run's file."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rerun as rr

from services.facts.run import RunFacts
from services.hot.read import read_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.messages import ArrowMessage, StoreKind

Chunks = list[tuple[ArrowMessage, ChunkMeta]]


def record(path: Path, log: Callable[[rr.RecordingStream], None], **fleet: Any) -> Path:
    """A recording made by `log`, with a `fleet` property of the `fleet` fields given."""
    rec = rr.RecordingStream("rules-tests", recording_id=path.stem)
    rec.save(str(path))
    if fleet:
        rec.send_property("fleet", rr.AnyValues(**fleet))
    log(rec)
    rec.flush()
    rec.disconnect()
    return path


def chunks(path: Path) -> Chunks:
    """The recording's data chunks (property chunks left out, as ingest hands them to rules), in file order."""
    found = []
    for event in read_events(path, path.stat().st_size):
        if isinstance(event, ArrowMessage) and event.store_id.kind == StoreKind.RECORDING:
            meta = chunk_meta(event)
            if not meta.entity_path.startswith("/__properties"):
                found.append((event, meta))
    return found


def properties(path: Path) -> dict[str, dict[str, Any]]:
    """The recording's properties as the catalog keeps them (what the run's facts learnt)."""
    facts = RunFacts("run", dt.datetime.now(dt.UTC))
    for event in read_events(path, path.stat().st_size):
        facts.replay(event, facts.created_at)
    return facts.properties


def seconds(ns: int) -> float:
    return ns / 1e9
