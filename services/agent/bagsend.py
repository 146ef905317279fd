"""Uploading the closed MCAP files `bags.BagScanner` finds: one at a time, each once, to the depot's
`POST /v1/uploads?run_id=RUN&application=APP` (the depot tells MCAP from .rrd by its magic bytes).

The body is streamed from the file (constant memory, file reads on worker threads), under the
agent's bandwidth cap at the lowest priority (with pulls): a bag of gigabytes must not hold back
live data or a trigger's window. What the depot took or refused is remembered in the agent's state
with the file's inode, size and mtime, so a restart sends nothing twice, and a file that changed
after it was sent is sent again (the depot files the same bag once). The depot's answers:

- 2xx: uploaded; its import id is kept.
- 401, 403: the robot's token is refused. Retried every minute, not held against the bag: a new
  token (and a restart) fixes it, as for the agent's streams.
- 408, 429, 5xx (503: the run's node is not ready; 507: the depot is full), or no answer: the link
  or the depot, not the bag. Retried with the agent's backoff.
- any other 4xx: the depot refuses this bag (not MCAP, damaged, another robot's run). Logged and
  kept as failed; it is sent again only if the file changes (`touch` it to try again).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from services.agent.bags import Bag, BagScanner, Stamp
from services.agent.bandwidth import Priority, TokenBucket
from services.agent.link import Backoff, DepotRefused, LinkDown
from services.agent.state import AgentState, BagRecord

log = logging.getLogger("fleet.agent")

RESCAN_S = 5.0  # how often the watched folders are walked for new or closed MCAP files
PIECE = 128 * 1024  # bytes read and sent at a time: small enough that a capped uplink stays smooth
CONNECT_S = 10.0
WRITE_S = 60.0  # a write the depot does not take for this long: the link is silent, try again later
# The depot answers once it has filed the whole bag, which takes longer the bigger the bag: wait
# a base, plus a second for every 10 MB of it.
READ_BASE_S = 300.0
READ_BYTES_PER_S = 10_000_000
BACKOFF_FIRST_S = 1.0
BACKOFF_MAX_S = 60.0  # a retry resends the whole file: not every few seconds
UPLOADED, FAILED = "uploaded", "failed"


class BagRejected(Exception):
    """The depot refused this bag (a 4xx that waiting does not change)."""


@dataclass
class BagCounts:
    """Where the bags stand, for `fleet agent status` and /metrics."""

    pending: int = 0  # found and not yet uploaded: still written, waiting for the link, or being sent
    uploaded: int = 0
    failed: int = 0
    bytes_uploaded: int = 0  # since the agent started
    uploads: int = 0  # since the agent started
    uploading: str | None = None  # the file being sent now
    error: str | None = None  # why the last attempt did not reach the depot (None: it did)

    def as_dict(self) -> dict[str, Any]:
        return dict(vars(self))


def timeout_for(size: int) -> httpx.Timeout:
    return httpx.Timeout(CONNECT_S, read=READ_BASE_S + size / READ_BYTES_PER_S, write=WRITE_S, pool=CONNECT_S)


def depot_error(response: httpx.Response) -> str:
    """The depot's `{"error": {"code", "message"}}` (or a flat `{"code", "message"}`) as one line."""
    try:
        body = response.json()
    except ValueError:
        return f"{response.status_code}: {response.text[:300]}"
    error = body.get("error", body) if isinstance(body, dict) else {}
    if not isinstance(error, dict):
        return f"{response.status_code}: {error}"
    return f"{response.status_code} {error.get('code', '')}: {error.get('message', '')}".strip()


async def upload_bag(client: httpx.AsyncClient, bag: Bag, bucket: TokenBucket | None = None) -> dict[str, Any]:
    """Send `bag`'s file (its first `bag.stamp.size` bytes) and return the depot's answer. Raises
    BagRejected, DepotRefused or LinkDown (see the module's docstring), or OSError when the file
    cannot be read (gone, or shorter than it was)."""
    size = bag.stamp.size
    fh = await asyncio.to_thread(open, bag.path, "rb")

    async def pieces() -> AsyncIterator[bytes]:
        left = size
        while left > 0:
            piece = await asyncio.to_thread(fh.read, min(PIECE, left))
            if not piece:
                raise OSError(f"{bag.path} is shorter than the {size} bytes it had")
            if bucket is not None:
                await bucket.acquire(len(piece), Priority.PULL)
            left -= len(piece)
            yield piece

    try:
        response = await client.post(
            "/v1/uploads",
            params={"run_id": bag.run_id, "application": bag.application},
            content=pieces(),
            headers={"Content-Type": "application/octet-stream", "Content-Length": str(size)},
            timeout=timeout_for(size),
        )
    except httpx.TransportError as exc:
        raise LinkDown(f"uploading {bag.path}: {type(exc).__name__}: {exc}") from exc
    finally:
        fh.close()
    status = response.status_code
    if status < 300:
        try:
            answer: dict[str, Any] = response.json()
        except ValueError:
            answer = {}
        return answer
    if status in (401, 403):
        raise DepotRefused(depot_error(response))
    if status in (408, 429) or status >= 500:
        raise LinkDown(f"depot answered {depot_error(response)}")
    raise BagRejected(depot_error(response))


def depot_client(
    api_url: str, token: str | None, *, transport: httpx.AsyncBaseTransport | None = None
) -> httpx.AsyncClient:
    """The agent's own client for bag uploads: `FleetClient.upload` sends an .rrd (no run id, no
    application) and would hold a worker thread for the whole of a file of gigabytes; this one
    streams on the event loop. It carries the robot's token as the link's REST client does."""
    headers = {"X-Fleet-User": "fleet-agent"}
    if token:
        headers["Authorization"] = f"Bearer {token.strip()}"
    return httpx.AsyncClient(base_url=api_url.rstrip("/"), headers=headers, transport=transport)


class BagSender:
    """Walks the watched folders every `RESCAN_S` and uploads each closed MCAP file, one at a time."""

    def __init__(
        self,
        directories: Sequence[str | os.PathLike[str]],
        state: AgentState,
        client: httpx.AsyncClient,
        *,
        bucket: TokenBucket | None = None,
        idle_s: float,
        rescan_s: float = RESCAN_S,
        on_answer: Callable[[], None] | None = None,
    ) -> None:
        self.directories = [Path(d).absolute() for d in directories]
        self.state, self.client, self.bucket = state, client, bucket
        self.scanner = BagScanner(idle_s)
        self.rescan_s = rescan_s
        self.on_answer = on_answer  # called with no argument when the depot answered (the link is up)
        self.records: dict[str, BagRecord] = state.bags()
        self.counts = BagCounts()
        self._pending: set[str] = set()
        self.backoff = Backoff(BACKOFF_FIRST_S, BACKOFF_MAX_S)
        self._recount()

    async def run(self) -> None:
        """Scan and upload until cancelled."""
        while True:
            try:
                await self.step()
            except Exception:  # never the end of the loop: said, and tried again
                log.exception("uploading watched MCAP files failed")
            await asyncio.sleep(self.rescan_s)

    async def step(self) -> None:
        """One pass: find what is closed, upload it in order, stop at the first failure of the link
        (the rest waits for the next pass, after the backoff)."""
        settled = {path: Stamp(r.inode, r.size, r.mtime_ns) for path, r in self.records.items()}
        scan = await asyncio.to_thread(self.scanner.scan, self.directories, settled)
        self._pending = set(scan.pending)
        await self._forget_gone(scan.found, scan.roots)
        self._recount()
        for bag in scan.closed:
            if not await self.send(bag):
                break

    async def send(self, bag: Bag) -> bool:
        """Upload one bag and remember the outcome; False if the link (or the token) failed."""
        if not bag.is_mcap:
            await self._settle(bag, FAILED, error="not an MCAP file (it does not start with MCAP's magic bytes)")
            log.warning("%s is not an MCAP file: not sent (it is looked at again if it changes)", bag.path)
            return True
        self.counts.uploading = bag.path
        log.info("uploading %s (%d bytes, closed: %s) to run %s", bag.path, bag.stamp.size, bag.why, bag.run_id)
        try:
            answer = await upload_bag(self.client, bag, self.bucket)
        except BagRejected as exc:
            self._answered()
            await self._settle(bag, FAILED, error=str(exc))
            log.warning("the depot refused %s (%s): not sent again unless the file changes", bag.path, exc)
            return True
        except DepotRefused as exc:
            self.counts.error = f"refused: {exc}"
            log.error("the depot refused the robot's upload of %s (%s): retried every minute", bag.path, exc)
            await self.backoff.wait(refused=True)
            return False
        except LinkDown as exc:
            self.counts.error = str(exc)
            # one warning when the depot stops answering, not one a minute until it answers again
            say = log.warning if self.backoff.failures == 0 else log.debug
            say("%s not uploaded (%s): tried again", bag.path, exc)
            await self.backoff.wait()
            return False
        except OSError as exc:  # gone, cut short or unreadable since the scan: this file, not the link
            self.counts.error = f"{bag.path}: {exc}"
            log.warning("%s could not be read (%s): looked at again at the next scan", bag.path, exc)
            return True
        finally:
            self.counts.uploading = None
        self._answered()
        self.backoff.reset()
        imported = answer.get("import")
        if not isinstance(imported, dict):  # a depot that says nothing of the import: no id to keep
            imported = {}
        import_id = str(imported["id"]) if imported.get("id") is not None else None
        await self._settle(bag, UPLOADED, import_id=import_id)
        self.counts.uploads += 1
        self.counts.bytes_uploaded += bag.stamp.size
        log.info(
            "uploaded %s to run %s (import %s%s)",
            bag.path,
            bag.run_id,
            import_id,
            ", already held" if imported.get("already_held") else "",
        )
        return True

    def _answered(self) -> None:
        self.counts.error = None
        if self.on_answer is not None:
            self.on_answer()

    async def _settle(self, bag: Bag, state: str, *, import_id: str | None = None, error: str | None = None) -> None:
        s = bag.stamp
        record = BagRecord(bag.path, bag.run_id, bag.application, s.inode, s.size, s.mtime_ns, state, import_id, error)
        await asyncio.to_thread(self.state.save_bag, record)
        self.records[bag.path] = record
        self._pending.discard(bag.path)
        self._recount()

    async def _forget_gone(self, found: set[str], roots: tuple[str, ...]) -> None:
        """Forget the files deleted since they were sent (the state does not grow with every bag
        ever recorded); not those under a folder that is missing now (unmounted: they come back)."""
        gone = [p for p in self.records if p not in found and any(p.startswith(r + os.sep) for r in roots)]
        for path in gone:
            with contextlib.suppress(KeyError):
                del self.records[path]
            await asyncio.to_thread(self.state.forget_bag, path)

    def _recount(self) -> None:
        settled = [r for p, r in self.records.items() if p not in self._pending]
        self.counts.pending = len(self._pending)
        self.counts.uploaded = sum(r.state == UPLOADED for r in settled)
        self.counts.failed = sum(r.state == FAILED for r in settled)
