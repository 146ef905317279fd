"""Serving a run as an `.rrd` stream: whole or filtered by entity, chunk payloads copied untouched.

The output is one RRD stream with the run's own SDK version in its header, store infos first, the
blueprint unless left out, and a footer with a manifest, written as it is produced (constant
memory). A live run is served as it stands when the request starts (whole messages only), or
followed (`follow_run`) until it closes.
"""

from __future__ import annotations

import datetime as dt
import io
import logging
import re
from collections.abc import AsyncIterator, Iterable, Iterator, Mapping
from contextlib import aclosing
from dataclasses import dataclass, field
from typing import BinaryIO, cast

import anyio.to_thread

from core.errors import BadParameterError
from services.hot.read import HotReader, HotRecording, follow_sizes
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.encoder import RrdEncoder
from services.rrd.entity_patterns import check_entity_patterns
from services.rrd.errors import RrdError
from services.rrd.frames import DEFAULT_VERSION
from services.rrd.manifest import is_property_entity
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    Event,
    StoreInfoMessage,
    StoreKind,
    StreamStart,
)
from services.runs.trim import trim

log = logging.getLogger(__name__)

FLUSH_BYTES = 1024 * 1024
PASS_THROUGH_BYTES = 256 * 1024  # a piece this large is sent as it is rather than joined with others
# A follower decodes what was just appended on the event loop (a chunk or a few: well under a
# millisecond); a bigger piece, such as the run so far, goes to a worker thread.
ON_LOOP_BYTES = 16 * 1024


@dataclass(frozen=True)
class EntityFilter:
    """Rerun's entity path patterns: `/world/**` is the subtree (with `/world`), anything else the
    exact path; no include means everything; exclude wins. The recording's properties are kept
    unless an exclude names them (`/__properties`, `/__properties/**` or a path below)."""

    include: list[str] = field(default_factory=list)
    exclude: list[str] = field(default_factory=list)
    # verdict per entity path: a run has few entities and many chunks, so each path is matched once
    _verdicts: dict[str, bool] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_entity_patterns("include", self.include)
        check_entity_patterns("exclude", self.exclude)

    def __call__(self, path: str) -> bool:
        verdict = self._verdicts.get(path)
        if verdict is None:
            verdict = self._verdicts[path] = self._decide(path)
        return verdict

    def _decide(self, path: str) -> bool:
        if is_property_entity(path):  # only an exclude that names the properties drops them
            return not any(is_property_entity(p.removesuffix("/**")) and _matches(p, path) for p in self.exclude)
        if any(_matches(p, path) for p in self.exclude):
            return False
        return not self.include or any(_matches(p, path) for p in self.include)

    def unmatched(self, paths: Iterable[str]) -> list[str]:
        """A warning for each pattern that matches none of `paths` (the run's entities): such a
        filter does nothing, most often because `/a` was meant as the subtree `/a/**`."""
        paths = set(paths)
        warnings = []
        for kind, patterns in (("include", self.include), ("exclude", self.exclude)):
            for pattern in patterns:
                if any(_matches(pattern, path) for path in paths):
                    continue
                below = not pattern.endswith("/**") and any(p.startswith(pattern.rstrip("/") + "/") for p in paths)
                hint = f" (its subtree is {pattern.rstrip('/')}/**)" if below else ""
                warnings.append(f"{kind} {pattern} matches no entity of the run{hint}")
        return warnings


def _matches(pattern: str, path: str) -> bool:
    if pattern.endswith("/**"):
        root = pattern[:-3].rstrip("/")
        return path == (root or "/") or path.startswith(root + "/")
    return path == pattern


class _Chunks(io.RawIOBase):
    """A sink the encoder writes to; the bytes are handed out in pieces as they accumulate. A large
    piece that is a view of immutable bytes (a chunk read by range) is held and handed out as it is,
    not copied; anything else is copied, as the buffer it lives in may be reused."""

    def __init__(self) -> None:
        self.pending: list[bytes | memoryview] = []
        self.size = 0

    def writable(self) -> bool:
        return True

    def write(self, data: object) -> int:
        piece: bytes | memoryview
        if isinstance(data, memoryview) and isinstance(data.obj, bytes) and len(data) >= PASS_THROUGH_BYTES:
            piece = data
        else:
            piece = bytes(data)  # type: ignore[call-overload]
        self.pending.append(piece)
        self.size += len(piece)
        return len(piece)

    def take(self) -> bytes:
        out = b"".join(self.pending)
        self.pending, self.size = [], 0
        return out

    def take_pieces(self) -> Iterator[bytes | memoryview]:
        """What is pending, the small pieces joined and the large ones as they are."""
        pending, self.pending, self.size = self.pending, [], 0
        small: list[bytes | memoryview] = []
        for piece in pending:
            if len(piece) < PASS_THROUGH_BYTES:
                small.append(piece)
                continue
            if small:
                yield b"".join(small)
                small = []
            yield piece
        if small:
            yield b"".join(small)


@dataclass(frozen=True)
class TimeWindow:
    """Chunks overlapping [start, end] on `timeline` (inclusive; None = open); with `latest_at`, also
    per entity and component the chunk(s) holding its newest row before `start`, so the scene at `start`
    is complete (see services.runs.latest_at)."""

    timeline: str
    start: int | None = None
    end: int | None = None
    latest_at: bool = True
    exact: bool = False  # cut chunks to the rows in the window and the latest-at rows (re-encoded, new ids)

    @property
    def bounds(self) -> tuple[int, int]:
        return (self.start if self.start is not None else -(2**63), self.end if self.end is not None else 2**63 - 1)


_UNITS_NS = {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000, "m": 60_000_000_000, "h": 3_600_000_000_000}
_DURATION = re.compile(r"^(-?\d+(?:\.\d+)?)(ns|us|ms|s|m|h)$")
_ISO = re.compile(r"^(\d{4}-\d{2}-\d{2}(?:[T ]\d{2}:\d{2}(?::\d{2})?)?)(?:\.(\d{1,9}))?(Z|[+-]\d{2}:?\d{2})?$")


TIME_MIN, TIME_MAX = -(2**63), 2**63 - 1  # Rerun's time values are signed 64-bit


def parse_time_value(name: str, timeline_type: str, text: str) -> int:
    """A `start`/`end` value by the timeline's type: sequence integers; durations like `12.5s`,
    `250ms` or ns; timestamps as ISO-8601 (to the nanosecond) or ns since the epoch."""
    value = _time_value(name, timeline_type, text)
    if not TIME_MIN <= value <= TIME_MAX:
        raise BadParameterError(
            name,
            f"{text!r} is outside the range of {timeline_type} values (signed 64-bit: "
            f"{TIME_MIN} to {TIME_MAX} ns, about 1677-09-21 to 2262-04-11 as timestamps)",
        )
    return value


def _time_value(name: str, timeline_type: str, text: str) -> int:
    if re.fullmatch(r"-?\d+", text):
        return int(text)
    if timeline_type == "duration" and (m := _DURATION.match(text)):
        number, unit = m.groups()
        whole, _, frac = number.partition(".")
        scale = _UNITS_NS[unit]
        value = abs(int(whole)) * scale + (int(frac.ljust(9, "0")[:9]) * scale // 10**9 if frac else 0)
        return -value if number.startswith("-") else value
    if timeline_type == "timestamp" and (m := _ISO.match(text)):
        base, frac, zone = m.groups()
        try:
            stamp = dt.datetime.fromisoformat(base + (zone or "").replace("Z", "+00:00"))
        except ValueError:
            stamp = None
        if stamp is not None:
            stamp = stamp if stamp.tzinfo else stamp.replace(tzinfo=dt.UTC)
            seconds = int(stamp.timestamp())
            return seconds * 1_000_000_000 + int((frac or "0").ljust(9, "0"))
    forms = {
        "sequence": "an integer",
        "duration": "a duration like 12.5s, 250ms or nanoseconds",
        "timestamp": "ISO-8601 like 2026-11-21T08:00:00.5Z, or nanoseconds since the epoch",
    }
    accepted = forms.get(timeline_type, "an integer")
    raise BadParameterError(name, f"{text!r} is not a {timeline_type} value: use {accepted}")


def window_from_query(
    types: dict[str, str],
    timeline: str | None,
    start: str | None,
    end: str | None,
    latest_at: bool,
    exact: bool = False,
) -> TimeWindow | None:
    """The time window of a request; BadParameterError naming what is wrong and what is accepted."""
    if timeline is None:
        if exact:
            raise BadParameterError("exact", "exact=true trims rows to a time window: give timeline, start, end")
        if start is not None or end is not None:
            raise BadParameterError("timeline", f"start/end need a timeline: one of {', '.join(sorted(types))}")
        return None
    if timeline not in types:
        raise BadParameterError(
            "timeline", f"{timeline!r} is not a timeline of this run: {', '.join(sorted(types)) or 'it has none'}"
        )
    kind = types[timeline]
    lo = parse_time_value("start", kind, start) if start is not None else None
    hi = parse_time_value("end", kind, end) if end is not None else None
    if lo is not None and hi is not None and lo > hi:
        raise BadParameterError("end", f"end {end!r} is before start {start!r}")
    return TimeWindow(timeline, lo, hi, latest_at, exact)


async def follow_run(hot: HotRecording, entities: EntityFilter, *, blueprint: bool = True) -> AsyncIterator[bytes]:
    """A live run as an RRD stream: what it holds, then what is written to it as it comes, ending
    with the footer when the run closes. The waiting is done on the event loop (a quiet follower
    holds no thread); a big piece (the run so far) is read and encoded on a worker thread."""
    reader = HotReader(hot.path)
    run = RunEncoder(entities, blueprint=blueprint)

    def step(size: int) -> bytes:
        for event in reader.read(size):
            run.add(event)
        return run.take() if run.pending >= FLUSH_BYTES else b""

    try:
        async with aclosing(follow_sizes(hot)) as sizes:
            async for size in sizes:
                while reader.position < size:
                    before = reader.position
                    if size - before <= ON_LOOP_BYTES:
                        piece = step(size)
                    else:  # not cancellable part-way: the reader is never closed under a step
                        piece = await anyio.to_thread.run_sync(step, size)
                    if piece:
                        yield piece
                    if reader.position == before:
                        break  # the file is shorter than said: what it holds was read
                if run.pending:  # caught up: send what is held before waiting
                    yield run.take()
        for event in reader.finish():
            run.add(event)
        yield run.finish()
    finally:
        reader.close()


class RunEncoder:
    """The chosen messages of a run encoded as one RRD stream with a footer, an event at a time; the
    bytes are taken out as they accumulate. With an exact window, recording chunks are cut to the
    rows in it plus their `picks` (latest-at rows)."""

    def __init__(
        self,
        entities: EntityFilter,
        *,
        blueprint: bool,
        window: TimeWindow | None = None,
        keep: set[bytes] | None = None,
        picks: dict[bytes, set[int]] | None = None,
        metas: Mapping[int, ChunkMeta] | None = None,
    ) -> None:
        self.entities, self.blueprint, self.window, self.keep = entities, blueprint, window, keep
        self.picks = picks or {}
        self.metas = metas if metas is not None else {}  # may be filled as the run is read
        self._sink = _Chunks()
        self._out = cast(BinaryIO, self._sink)
        self._encoder: RrdEncoder | None = None
        self.chunks = 0  # recording chunks encoded so far

    @property
    def pending(self) -> int:
        """Bytes encoded and not taken yet."""
        return self._sink.size

    def take(self) -> bytes:
        return self._sink.take()

    def take_pieces(self) -> Iterator[bytes | memoryview]:
        """What is encoded and not taken yet, large chunks as they are (not joined, not copied)."""
        return self._sink.take_pieces()

    def add(self, event: Event) -> None:
        if isinstance(event, StreamStart):
            self._encoder = self._encoder or RrdEncoder(self._out, event.version)  # the run's own SDK version
            return
        if not isinstance(event, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage):
            return
        encoder = self._encoder = self._encoder or RrdEncoder(self._out, DEFAULT_VERSION)
        store = event.blueprint_id if isinstance(event, BlueprintActivationMessage) else event.store_id
        if store.kind == StoreKind.BLUEPRINT and not self.blueprint:
            return
        if not isinstance(event, ArrowMessage):
            encoder.write(event)
            return
        try:
            meta = self.metas.get(event.offset) or chunk_meta(event)
        except RrdError as exc:  # stored before ingest refused such chunks: the download goes on without it
            log.warning("a stored chunk is left out of a download, as it cannot be read: %s", exc)
            return
        if store.kind == StoreKind.RECORDING and not self.entities(meta.entity_path):
            return
        if self.keep is not None and meta.chunk_id not in self.keep:
            return
        window = self.window
        if window is not None and window.exact and store.kind == StoreKind.RECORDING and not meta.is_static:
            lo, hi = window.bounds
            try:
                cut = trim(event, meta, window.timeline, lo, hi, self.picks.get(meta.chunk_id, ()))
            except RrdError as exc:  # a chunk stored before ingest refused it: sent as stored, never a cut stream
                log.warning("a stored chunk is sent whole in an exact download, as it cannot be read: %s", exc)
                cut = (event, meta)
            if cut is None:
                return
            event, meta = cut
        encoder.write_arrow(event, meta)
        self.chunks += store.kind == StoreKind.RECORDING

    def finish(self) -> bytes:
        """The rest of the stream: what is held, the End message and the footer."""
        (self._encoder or RrdEncoder(self._out, DEFAULT_VERSION)).finish()
        return self._sink.take()


def encode_run(
    events: Iterable[Event],
    entities: EntityFilter,
    *,
    blueprint: bool,
    window: TimeWindow | None,
    keep: set[bytes] | None,
    picks: dict[bytes, set[int]],
    metas: Mapping[int, ChunkMeta],
) -> Iterator[bytes | memoryview]:
    """The chosen messages of a run as one RRD stream with a footer (`RunEncoder`), in pieces of
    about 1 MiB (a large chunk read by range as a piece of its own, not copied). The first piece goes
    out as soon as it holds a recording chunk: a window of a small entity is well under 1 MiB, and
    the viewer shows its first chunk while the others are read."""
    run = RunEncoder(entities, blueprint=blueprint, window=window, keep=keep, picks=picks, metas=metas)
    sent = False
    for event in events:
        run.add(event)
        if run.pending >= FLUSH_BYTES or (not sent and run.chunks):
            sent = True
            yield from run.take_pieces()
    yield run.finish()
