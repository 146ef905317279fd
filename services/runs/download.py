"""Serving a run as an `.rrd` stream: whole or filtered by entity, chunk payloads copied untouched.

The output is one RRD stream with the run's own SDK version in its header, store infos first, the
blueprint unless left out, and a footer with a manifest, written as it is produced (constant
memory). A live run is served as it stands when the request starts (whole messages only).
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, cast

from services.ingest.service import IngestService
from services.rrd.chunk import chunk_meta
from services.rrd.decoder import iter_events
from services.rrd.encoder import RrdEncoder
from services.rrd.frames import RerunVersion
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    StoreInfoMessage,
    StoreKind,
    StreamStart,
)
from services.runs.service import BadParameterError, RunNotFoundError

FLUSH_BYTES = 1024 * 1024
DEFAULT_VERSION = RerunVersion(0, 41, 0)


@dataclass(frozen=True)
class EntityFilter:
    """Rerun's entity path patterns: `/world/**` is the subtree (with `/world`), anything else the
    exact path; no include means everything; exclude wins."""

    include: list[str] = field(default_factory=list)
    exclude: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name, patterns in (("include", self.include), ("exclude", self.exclude)):
            for pattern in patterns:
                if not pattern.startswith("/") or "**" in pattern[:-2]:
                    raise BadParameterError(name, f"{pattern!r} is not an entity path pattern: use /a/b (that "
                                                  "entity) or /a/** (the subtree)")

    def __call__(self, path: str) -> bool:
        if any(_matches(p, path) for p in self.exclude):
            return False
        return not self.include or any(_matches(p, path) for p in self.include)


def _matches(pattern: str, path: str) -> bool:
    if pattern.endswith("/**"):
        root = pattern[:-3].rstrip("/")
        return path == (root or "/") or path.startswith(root + "/")
    return path == pattern


class _Chunks(io.RawIOBase):
    """A sink the encoder writes to; the bytes are handed out in pieces as they accumulate."""

    def __init__(self) -> None:
        self.pending: list[bytes] = []
        self.size = 0

    def writable(self) -> bool:
        return True

    def write(self, data: object) -> int:
        piece = bytes(data)  # type: ignore[call-overload]
        self.pending.append(piece)
        self.size += len(piece)
        return len(piece)

    def take(self) -> bytes:
        out = b"".join(self.pending)
        self.pending, self.size = [], 0
        return out


class _Bounded(io.RawIOBase):
    """The first `limit` bytes of a file: a live run is read as it stood when the request began."""

    def __init__(self, path: Path, limit: int) -> None:
        self._fh = open(path, "rb")  # noqa: SIM115 - closed by close()
        self._left = limit

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: object) -> int:
        view = memoryview(buffer)  # type: ignore[arg-type]
        n = self._fh.readinto(view[: min(len(view), self._left)]) or 0
        self._left -= n
        return n

    def close(self) -> None:
        self._fh.close()
        super().close()


def stream_run(path: Path, size: int, entities: EntityFilter, *, blueprint: bool = True) -> Iterator[bytes]:
    """The run in `path` (its first `size` bytes) as an RRD stream, in pieces of about 1 MiB."""
    sink = _Chunks()
    out = cast(BinaryIO, sink)
    encoder: RrdEncoder | None = None
    with _Bounded(path, size) as source:
        for event in iter_events(cast(BinaryIO, source)):
            if isinstance(event, StreamStart):
                encoder = encoder or RrdEncoder(out, event.version)  # the run's own SDK version
                continue
            if not isinstance(event, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage):
                continue
            encoder = encoder or RrdEncoder(out, DEFAULT_VERSION)
            store = event.blueprint_id if isinstance(event, BlueprintActivationMessage) else event.store_id
            if store.kind == StoreKind.BLUEPRINT and not blueprint:
                continue
            if isinstance(event, ArrowMessage):
                meta = chunk_meta(event)
                if store.kind == StoreKind.RECORDING and not entities(meta.entity_path):
                    continue
                encoder.write_arrow(event, meta)
            else:
                encoder.write(event)
            if sink.size >= FLUSH_BYTES:
                yield sink.take()
    (encoder or RrdEncoder(out, DEFAULT_VERSION)).finish()
    yield sink.take()


def locate(ingest: IngestService, run_id: str) -> tuple[Path, int]:
    """The hot file of a run and how many bytes of it are whole messages now."""
    run = ingest.runs.get(run_id)
    if run is None:
        raise RunNotFoundError(f"no run {run_id!r}: list runs with GET /v1/runs or `fleet runs ls`")
    return run.hot.path, run.hot.size
