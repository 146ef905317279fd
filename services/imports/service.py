"""Uploads as imports: an upload's body told apart by its first bytes (MCAP's magic, else RRD),
recorded in the catalog from its first byte to its end, filed through ingest; a failed MCAP import
retried from its quarantined original. Blocking work (files, the catalog, the converter) runs on
worker threads; the event loop only moves bytes and messages.
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import json
import logging
from collections.abc import AsyncIterator, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from starlette.requests import ClientDisconnect

from catalog import imports as rows
from catalog.db import session_scope
from core.errors import (
    BadParameterError,
    ConflictError,
    FleetError,
    InsufficientStorageError,
    InvalidMcapError,
    PermissionDeniedError,
    UnavailableError,
)
from services.auth.scopes import Principal
from services.auth.tokens import Auth
from services.imports import mcap_import
from services.imports.mcap_file import MAGIC, is_mcap
from services.imports.mcap_import import Asked, Converted, Converter, Held
from services.imports.records import Ledger, run_ids_of
from services.imports.uploads import CLIENT_GONE, Filed, file_events
from services.ingest.service import IngestService
from services.rrd.decoder import RrdDecoder
from services.rrd.messages import Event
from services.storage.objectstore import RangeReader

log = logging.getLogger(__name__)
WRITE_BYTES = 4 << 20  # an MCAP body is written to its staging file in pieces of about this size
READ_BYTES = 1 << 20


@dataclass(frozen=True)
class UploadAsk:
    """An upload's query: the file's name, and for MCAP the run, application and robot."""

    name: str = ""
    run_id: str | None = None
    application: str | None = None
    robot: str | None = None


@dataclass(frozen=True)
class Importer:
    ingest: IngestService
    auth: Auth
    ledger: Ledger
    converter: Converter
    max_message_size: int
    max_chunk_bytes: int

    async def upload(
        self, body: AsyncIterator[bytes], principal: Principal, who: str, authorization: str | None, ask: UploadAsk
    ) -> Filed:
        head, pieces = await _peek(body, len(MAGIC))
        if is_mcap(head):
            return await self._mcap(pieces, principal, who, authorization, ask)
        if ask.run_id is not None or ask.application is not None or ask.robot is not None:
            raise BadParameterError(
                "run_id", "run_id, application and robot apply to MCAP uploads: an .rrd file names its own recording"
            )
        return await self._rrd(pieces, principal, who, authorization, ask.name)

    async def _rrd(
        self, pieces: AsyncIterator[bytes], principal: Principal, who: str, authorization: str | None, name: str
    ) -> Filed:
        """An `.rrd` body filed as it arrives. Its import row is written beside it, never in its way:
        the upload neither waits for the catalog to start it nor to end it (a catalog outage must not
        stop uploads), so the answer names the import only if its row was written by then."""
        started = _background(self._best_effort(self.ledger.start, "rrd", name, who, principal.robot))
        received = 0

        async def counted() -> AsyncIterator[bytes]:
            nonlocal received
            async for piece in pieces:
                received += len(piece)
                yield piece

        source = self.ingest.open_source(live=False, robot=principal.robot)
        filed = await file_events(self.ingest, self.auth, source, authorization, self._events(counted()))
        _background(self._end_rrd(started, received, filed))
        if started.done() and (import_id := started.result()) is not None:
            filed.body.update({"import": {"id": import_id, "kind": "rrd"}})
        return filed

    async def _end_rrd(self, started: asyncio.Task[Any], received: int, filed: Filed) -> None:
        import_id = await started
        if import_id is None:
            return
        if filed.status < 400:
            await self._best_effort(self.ledger.filed, import_id, received, filed.report)
        else:
            reason = str(filed.body.get("message") or filed.body.get("error", {}).get("code", "refused"))
            await self._best_effort(self.ledger.failed, import_id, received, reason, filed.report)

    async def _mcap(
        self, pieces: AsyncIterator[bytes], principal: Principal, who: str, authorization: str | None, ask: UploadAsk
    ) -> Filed:
        if principal.robot is not None and ask.robot is not None and ask.robot != principal.robot:
            raise PermissionDeniedError(f"this token files runs of robot {principal.robot} only, not of {ask.robot!r}")
        asked = Asked(ask.run_id, ask.application, principal.robot or ask.robot)
        try:
            import_id = await asyncio.to_thread(self.ledger.start, "mcap", ask.name or "upload.mcap", who, asked.robot)
        except Exception as exc:
            raise UnavailableError(
                f"the catalog does not answer ({type(exc).__name__}): an MCAP upload needs it to be filed once; "
                "send it again in a few seconds"
            ) from None
        original = self.converter.folder(import_id) / "original.mcap"
        try:
            received, digest = await _receive(pieces, original)
        except Exception as exc:  # the client went away, or the disk failed: nothing was filed or kept
            refusal = _receive_failure(exc)
            size = original.stat().st_size if original.exists() else 0
            await self._best_effort(self._fail, import_id, size, refusal or exc)
            if refusal is None:
                return Filed(CLIENT_GONE, {"error": {"code": "CLIENT_GONE"}}, {})
            raise refusal from None
        return await self._convert_and_file(import_id, original, received, digest, asked, authorization)

    async def retry(self, import_id: str, authorization: str | None) -> Filed:
        """Convert a failed MCAP import again from its quarantined original (after a rerun-sdk
        upgrade, or once a conflicting import ended)."""
        row = await asyncio.to_thread(self.ledger.row, import_id)
        if row.kind != "mcap" or row.state != rows.FAILED or not row.quarantine_key:
            raise ConflictError(
                f"import {import_id} is {row.state}{' (rrd)' if row.kind == 'rrd' else ''}: only a failed MCAP "
                "import whose original is in quarantine can be retried (an RRD upload: send the file again)"
            )
        original = self.converter.folder(import_id) / "original.mcap"
        digest = await asyncio.to_thread(self._fetch, row.quarantine_key, original)
        runs = run_ids_of(row)
        asked = Asked(runs[0] if runs else None, row.application_id, row.robot_id)
        await asyncio.to_thread(
            self.ledger.update, import_id, state=rows.RECEIVING, reason=None, node=self.ledger.node_id
        )
        return await self._convert_and_file(import_id, original, row.bytes, digest, asked, authorization)

    async def _convert_and_file(
        self, import_id: str, original: Path, received: int, digest: str, asked: Asked, authorization: str | None
    ) -> Filed:
        try:
            outcome = await asyncio.to_thread(
                mcap_import.prepare, self.ledger, self.converter, import_id, original, digest, asked
            )
        except Exception as exc:
            refusal = exc if isinstance(exc, FleetError) else _unexpected(import_id, exc)
            await self._best_effort(self._fail, import_id, received, refusal, original, digest)
            refused: dict[str, Any] = {**refusal.to_dict(), "import": self._summary(import_id, False)}
            return Filed(refusal.http_status(), refused, refusal.headers())
        if isinstance(outcome, Held):
            await self._best_effort(self._held, import_id, received, digest, outcome)
            body: dict[str, Any] = {"runs": [outcome.run_id], "chunks_new": 0, "chunks_duplicate": 0, "bytes_new": 0}
            body |= {"already_held": True, "import": self._summary(import_id, True, held_by=outcome.import_id)}
            return Filed(200, body, {})
        filed = await self._file(outcome, authorization)
        if filed.status < 400:
            await self._best_effort(self.ledger.filed, import_id, received, filed.report)
            await asyncio.to_thread(mcap_import.cleanup, self.converter, import_id)
        else:
            refused_by_ingest = InvalidMcapError(
                str(filed.body.get("message") or "the converted recording was refused")
            )
            await self._best_effort(self._fail, import_id, received, refused_by_ingest, original, digest, filed.report)
        filed.body.update({"already_held": False, "import": self._summary(import_id, False, extends=outcome.extends)})
        return filed

    async def _file(self, outcome: Converted, authorization: str | None) -> Filed:
        async def pieces() -> AsyncIterator[bytes]:
            with open(outcome.recording, "rb") as f:
                while piece := await asyncio.to_thread(f.read, READ_BYTES):
                    yield piece

        source = self.ingest.open_source(live=False, robot=outcome.robot)
        return await file_events(self.ingest, self.auth, source, authorization, self._events(pieces()))

    async def _events(self, pieces: AsyncIterator[bytes]) -> AsyncIterator[Event]:
        """The RRD messages of a body, decoded as its pieces come (an upload's, or a converted bag's)."""
        decoder = RrdDecoder(max_message_size=self.max_message_size, max_chunk_bytes=self.max_chunk_bytes)
        async for piece in pieces:
            for event in decoder.feed(piece):
                yield event
        for event in decoder.finish():
            yield event

    # --- on worker threads ----------------------------------------------------------------------

    def _fail(
        self,
        import_id: str,
        received: int,
        exc: BaseException,
        original: Path | None = None,
        digest: str | None = None,
        report: dict[str, Any] | None = None,
    ) -> None:
        """The import failed: why (and what of it was kept, `report`), the original kept in
        quarantine (unless the failure was another import's doing), the digest released."""
        reason = exc.message if isinstance(exc, FleetError) else f"{type(exc).__name__}: {exc}"
        self.ledger.failed(import_id, received, reason, report)
        self._release(import_id, digest)
        if original is not None and original.exists() and not isinstance(exc, ConflictError):
            self.ledger.quarantine(import_id, original, self.ledger.row(import_id).name)
        mcap_import.cleanup(self.converter, import_id)

    def _held(self, import_id: str, received: int, digest: str, held: Held) -> None:
        self.ledger.update(
            import_id,
            state=rows.FILED,
            bytes=received,
            digest=digest,
            held_by=held.import_id,
            run_ids=json.dumps([held.run_id]),
            reason=f"already held: the same file was filed by import {held.import_id}",
        )
        mcap_import.cleanup(self.converter, import_id)

    def _release(self, import_id: str, digest: str | None) -> None:
        if digest is not None:
            with session_scope(self.ledger.catalog, write=True) as session:
                rows.release(session, digest, import_id)

    def _fetch(self, key: str, target: Path) -> str:
        """The quarantined original back in staging; its digest."""
        warm = self.ledger.warm
        size = warm.head(key).size
        hasher = hashlib.sha256()
        reader = RangeReader(warm, key, size)
        with open(target, "wb") as out:
            while piece := reader.read(READ_BYTES * 8):
                hasher.update(piece)
                out.write(piece)
        return hasher.hexdigest()

    def _summary(self, import_id: str, already_held: bool, **more: Any) -> dict[str, Any]:
        """The import an MCAP upload made, as its answer names it."""
        found = {k: v for k, v in more.items() if v is not None}
        return {"id": import_id, "kind": "mcap", "already_held": already_held, **found}

    async def _best_effort(self, fn: Any, *args: Any) -> Any:
        """Bookkeeping an upload's answer does not wait on if the catalog fails: logged, not raised
        (the import row may then be stale; the data it names is filed or not as the answer says)."""
        try:
            return await asyncio.to_thread(fn, *args)
        except Exception as exc:
            log.warning("import bookkeeping skipped (%s: %s); the upload itself goes on", type(exc).__name__, exc)
            return None


async def _peek(body: AsyncIterator[bytes], count: int) -> tuple[bytes, AsyncIterator[bytes]]:
    """The first `count` bytes of `body` (fewer if it is shorter), and the whole body again."""
    head = b""
    async for piece in body:
        head += piece
        if len(head) >= count:
            break

    async def again() -> AsyncIterator[bytes]:
        if head:
            yield head
        async for piece in body:
            yield piece

    return head[:count], again()


async def _receive(pieces: AsyncIterator[bytes], target: Path) -> tuple[int, str]:
    """The body written to `target` (writes and hashing on a worker thread, in pieces of about
    WRITE_BYTES); its size and sha256."""
    hasher, received, pending = hashlib.sha256(), 0, bytearray()

    def flush(f: Any, data: bytes) -> None:
        hasher.update(data)
        f.write(data)

    with open(target, "wb") as f:
        async for piece in pieces:
            pending += piece
            received += len(piece)
            if len(pending) >= WRITE_BYTES:
                await asyncio.to_thread(flush, f, bytes(pending))
                pending.clear()
        await asyncio.to_thread(flush, f, bytes(pending))
    return received, hasher.hexdigest()


_BOOKKEEPING: set[asyncio.Task[Any]] = set()  # tasks under way, held so they are not collected


def _background(work: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
    task = asyncio.create_task(work)
    _BOOKKEEPING.add(task)
    task.add_done_callback(_BOOKKEEPING.discard)
    return task


def _receive_failure(exc: BaseException) -> FleetError | None:
    """What to answer when an MCAP body could not be kept: None if its client went away."""
    if isinstance(exc, ClientDisconnect):
        return None
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return InsufficientStorageError("the depot's disk is full: the MCAP file could not be kept; send it later")
    return UnavailableError(f"the MCAP file could not be kept ({type(exc).__name__}): send it again")


def _unexpected(import_id: str, exc: BaseException) -> FleetError:
    """A failure that is not the file's (the catalog, the disk): logged whole, answered 503."""
    log.error("import %s failed unexpectedly", import_id, exc_info=exc)
    return UnavailableError(
        f"the depot could not file the MCAP upload ({type(exc).__name__}): send it again; "
        f"`fleet imports show {import_id}` says how it ended"
    )
