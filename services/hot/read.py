"""Reading a hot run's file: its messages as they stand, and, when following a live run, those
appended after, until the run closes."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from services.rrd.decoder import RrdDecoder
from services.rrd.messages import Event

READ_BYTES = 1024 * 1024
FOLLOW_POLL_S = 0.1
# A live run's file: () -> (bytes of whole messages now, whether the run is still live).
Follow = Callable[[], tuple[int, bool]]


@dataclass(frozen=True)
class HotRecording:
    """A run in this node's hot tier as a reader sees it: its file as it stands, its timelines, and
    how to follow it."""

    path: Path
    size: int  # bytes of whole messages when the reader asked
    timeline_types: dict[str, str]
    follow: Follow


class HotRuns(Protocol):
    """The hot runs of this node, read-only: what serving and analytics may ask of ingest."""

    def hot_recording(self, run_id: str) -> HotRecording | None: ...


def read_events(path: Path, size: int, follow: Follow | None) -> Iterator[Event | None]:
    """Events of the first `size` bytes, then, with `follow`, of what is appended while the run is
    live; None marks a pause (the caller sends what it holds before waiting)."""
    decoder = RrdDecoder()
    position = 0
    with open(path, "rb") as fh:
        while True:
            while position < size:
                piece = fh.read(min(READ_BYTES, size - position))
                if not piece:
                    break
                position += len(piece)
                yield from decoder.feed(piece)
            if follow is None:
                break
            grown, live = follow()
            if grown > size:
                size = grown
                continue
            if not live:
                break
            yield None
            time.sleep(FOLLOW_POLL_S)  # waiting for the run to grow; ends when it closes
    yield from decoder.finish()
