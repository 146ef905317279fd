"""Forwarding one spooled run to the depot, and knowing how much of it the depot holds.

A run's messages are sent in the order they were spooled, on a gRPC stream of their own (so the
depot sees the run live while the robot streams it and closed when it ends). Where forwarding
stands is two offsets in the run file: `checked_until` (every forwarded message before it is known
to be at the depot) and `sent_until` (written to the stream). What lies between is in flight: after
a cut, a depot restart or an agent restart, the agent asks the depot which of those chunks it lacks
and sends only those, then carries on from `sent_until`. Data spooled while the link was down is
sent from the file behind the newest data (backfill), so live data goes first.

Every `check_s` the chunks sent before the previous check are asked about, so `checked_until`
advances and a later question stays small. Once the run is closed and all of it is held, the depot
is asked whether it is sealed in its warm tier: then the run is `confirmed`, and the robot may
delete it. Entities the live rules keep on the robot are skipped here (and counted as local-only).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import grpc

from services.agent.bandwidth import Priority, TokenBucket
from services.agent.lanes import Lane, PullJob
from services.agent.link import (
    Backoff,
    DepotLink,
    DepotRefused,
    LinkDown,
    cancelled,
    stream_ended,
    stream_failure,
)
from services.agent.spool import Spool
from services.agent.state import AgentState, RunState
from services.hot.index import HotEntry
from services.hot.tail import HotIndexTail
from services.ingest.replay import read_response
from services.rrd.chunk_index import CHUNK, STORE_INFO
from services.rrd.frames import MESSAGE_HEADER_SIZE, decode_message_header

log = logging.getLogger("fleet.agent")

BACKFILL_SPLIT_BYTES = 1 << 20  # a gap larger than this at reconnect is sent behind the newest data
LINGER_S = 5.0  # a closed run's stream stays open this long for more (a watched file still growing)
BATCH_BYTES = 1 << 20  # read from the spool file at once
SEALED = "warm"
PULL_CONFIRM_S = 1.0  # a written pull is asked about this often until the depot holds all of it


class Forwarding:
    """What every run's sender shares: the spool, the link, the bandwidth, the state and the rules."""

    def __init__(
        self,
        spool: Spool,
        link: DepotLink,
        bucket: TokenBucket,
        state: AgentState,
        forwards: Callable[[str], bool],
        check_s: float,
        stall_s: float,
    ) -> None:
        self.spool = spool
        self.link = link
        self.bucket = bucket
        self.state = state
        self.forwards = forwards  # entity path -> sent live (else kept on the robot until pulled)
        self.check_s = check_s
        self.stall_s = stall_s  # a write that waits longer: the link is silent, connect anew
        self.counters = {"messages_sent": 0, "bytes_sent": 0, "bytes_resent": 0, "chunks_resent": 0}


class RunSender:
    def __init__(self, ctx: Forwarding, run_id: str, state: RunState, *, fresh: bool) -> None:
        """`fresh`: a run this agent saw begin (nothing of it sent yet); else one an earlier agent
        process forwarded, from which anything up to the file's size may be in flight."""
        self.ctx = ctx
        self.run_id = run_id
        self.state = state
        self.fresh = fresh
        self.sent_until = state.checked_until
        self.check_mark: int | None = None  # sent_until at the previous check
        self.store_infos: list[HotEntry] = []
        self.lanes: list[Lane] = []
        self.wake = asyncio.Event()
        self.backoff = Backoff()
        self.started = False
        self.settled = False  # what was in flight at the last break was asked about
        self.streaming = False
        self.last_check = time.monotonic()
        self.last_confirm = time.monotonic()
        self.checks = 0
        self.last_append = time.monotonic()
        self.pulls: list[PullJob] = []
        self.local_only_entities: set[str] = set()  # entities the live rules kept on the robot
        self.learned = False  # what is on the robot only was asked of the depot (reported after that)
        self.holder: str | None = None  # the depot process last said to hold the run's unsealed chunks
        self.handed = False  # that changed: what it was said to hold is asked about again

    # --- the run as the spool holds it ------------------------------------------------------------

    def _run(self) -> Any:
        return self.ctx.spool.run(self.run_id)

    def _size(self) -> int:
        run = self._run()
        return run.size if run is not None else 0

    def _forwarded(self, entry: HotEntry) -> bool:
        if entry.kind != CHUNK or entry.meta is None:
            return True
        if entry.store_kind != "recording":
            return True  # blueprints are small and make the run look as the robot meant
        return self.ctx.forwards(entry.meta.entity_path)

    def _read(self, entries: list[HotEntry]) -> list[bytes]:
        """The frames of `entries` from the spool file (one read for neighbours), as requests."""
        run = self._run()
        if run is None:
            return []
        out: list[bytes] = []
        fd = os.open(run.path, os.O_RDONLY)
        try:
            for entry in entries:
                frame = os.pread(fd, entry.length, entry.offset)
                kind, length = decode_message_header(frame[:MESSAGE_HEADER_SIZE])
                out.append(read_response(kind, memoryview(frame)[MESSAGE_HEADER_SIZE : MESSAGE_HEADER_SIZE + length]))
        finally:
            os.close(fd)
        return out

    # --- the sender's life ------------------------------------------------------------------------

    async def run(self) -> None:
        """Forward until the run is confirmed (sealed at the depot) or removed from the spool."""
        try:
            await self._forward()
        finally:
            self.ctx.link.refusals.pop(self.run_id, None)  # nothing of it is sent any more

    async def _forward(self) -> None:
        while self._run() is not None and (not self.state.confirmed or self.pulls):
            try:
                await self._session()
                self.backoff.reset()
            except LinkDown as exc:
                self.ctx.link.mark_down(str(exc))
                self.lanes.clear()  # what was queued is re-read from the file at the next session
                self.settled = False
                await self.backoff.wait()
            except DepotRefused as exc:
                self.ctx.link.refusals[self.run_id] = str(exc)
                log.error("depot refused run %s: %s (retrying in a minute)", self.run_id, exc)
                self.lanes.clear()
                self.settled = False
                await self.backoff.wait(refused=True)
            except asyncio.CancelledError:
                if cancelled():
                    raise
                self.ctx.link.mark_down("a call to the depot was dropped")  # its channel was replaced
                self.lanes.clear()
                self.settled = False
                await self.backoff.wait()
            except Exception:  # a bug, or the spool's disk failing: said, and tried again later
                log.exception("forwarding run %s failed; retrying", self.run_id)
                self.lanes.clear()
                self.settled = False
                await self.backoff.wait(refused=True)

    async def _session(self) -> None:
        """One stream to the depot: settle what was in flight, then send until nothing is left."""
        if not self.started:
            if not self.fresh:
                self.sent_until = max(self.sent_until, self._size())  # what the last agent sent is unknown
            kept = await asyncio.to_thread(self._learn_run, self.sent_until)
            await self._learn_local_only(kept)
            self.started = True
        self.lanes = []
        if not self.settled:
            await self._settle_in_flight()
            self.settled = True
        self._plan_lanes()
        await self._plan_pulls()
        if not self._has_work():
            await self._idle()
            return
        call, generation = self.ctx.link.open_stream()
        self.streaming = True
        try:
            for request in await asyncio.to_thread(self._read, self.store_infos):
                await self._write(call, generation, request, Priority.LIVE)
            await self._pump(call, generation)
            await call.done_writing()
            await call
            self.ctx.link.mark_up()
            self.ctx.link.refusals.pop(self.run_id, None)  # the depot took this run's stream
        except (LinkDown, DepotRefused):
            call.cancel()
            raise
        except asyncio.CancelledError:
            call.cancel()
            if cancelled():
                raise
            raise LinkDown("the connection to the depot was dropped (silent link)") from None
        except (grpc.aio.AioRpcError, asyncio.InvalidStateError) as exc:  # the stream ended: refused or broken
            failure = await stream_ended(call, exc)  # (its status says which)
            call.cancel()
            raise failure from exc
        except Exception as exc:  # anything else: no status to wait for
            call.cancel()
            raise stream_failure(exc) from exc
        finally:
            self.streaming = False

    def _learn_run(self, passed: int) -> list[HotEntry]:
        """The run's store infos (sent first on every stream), and its chunks up to `passed` that the
        live rules now in force would keep on the robot (the lanes count those after it as they pass)."""
        self.store_infos, kept = self._scan(passed)
        return kept

    def _scan(self, passed: int) -> tuple[list[HotEntry], list[HotEntry]]:
        """The run's store infos, and its chunks up to `passed` the current live rules keep."""
        tail = HotIndexTail(self._run().path)
        size = self._size()
        infos: list[HotEntry] = []
        kept: list[HotEntry] = []
        while entries := tail.read(size):
            for entry in entries:
                if entry.kind == STORE_INFO:
                    infos.append(entry)
                elif entry.end <= passed and not self._forwarded(entry) and entry.meta is not None:
                    kept.append(entry)
        return infos, kept

    async def _learn_local_only(self, kept: list[HotEntry]) -> None:
        """Which chunks are on the robot only: of those the current rules keep, the ones the depot
        says it lacks. The rules may have been narrowed since an earlier agent sent them (a restart
        with another --live-include): only the depot knows what it holds."""
        self.local_only_entities = set()
        local: list[HotEntry] = []
        if kept:
            held = await self.ctx.link.held(self.run_id, [e.meta.chunk_id for e in kept if e.meta is not None])
            local = [e for e in kept if e.meta is not None and e.meta.chunk_id in held.missing]
        self.state.local_only_chunks = len(local)
        self.state.local_only_bytes = sum(e.length for e in local)
        self.local_only_entities = {e.meta.entity_path for e in local if e.meta is not None}
        self.learned = True
        self.ctx.state.save_run(self.state)

    async def _settle_in_flight(self) -> None:
        """Ask the depot which chunks in [checked_until, sent_until) it lacks; queue those."""
        start, end = self.state.checked_until, self.sent_until
        if end <= start:
            return
        entries = await asyncio.to_thread(self._entries, start, end)
        missing = await self._missing(entries)
        # blueprint activations are not chunks the depot can be asked about: sent again (it keeps one)
        missing += [e for e in entries if e.kind not in (CHUNK, STORE_INFO)]
        missing.sort(key=lambda e: e.offset)
        if missing:
            self.lanes.append(Lane(Priority.BACKFILL, entries=deque(missing), on_sent=self._count_resent))
            log.info("run %s: re-sending %d chunks the depot lacks", self.run_id, len(missing))
        else:
            self._checked(end)
        await self._recheck_if_handed()

    def _entries(self, start: int, end: int) -> list[HotEntry]:
        tail = HotIndexTail(self._run().path, start)
        out: list[HotEntry] = []
        while entries := tail.read(end):
            out += [e for e in entries if e.end <= end]
        return out

    async def _missing(self, entries: list[HotEntry], *, pulled: bool = False) -> list[HotEntry]:
        """The chunks of `entries` the depot lacks: of those forwarded live (or all, for a pull)."""
        chunks = [e for e in entries if e.kind == CHUNK and e.meta is not None and (pulled or self._forwarded(e))]
        if not chunks:
            return []
        held = await self.ctx.link.held(self.run_id, [e.meta.chunk_id for e in chunks if e.meta is not None])
        self.state.depot_tier = held.tier
        self._note_holder(held.holder)
        if not held.accepts_data:
            return []  # cold or deleted at the depot: nothing more can go
        return [e for e in chunks if e.meta is not None and e.meta.chunk_id in held.missing]

    def _note_holder(self, holder: str | None) -> None:
        if holder is None:
            return
        if self.holder is not None and holder != self.holder:
            log.info("run %s: held by another depot process now (%s): asking again what it holds", self.run_id, holder)
            self.handed = True
        self.holder = holder

    async def _recheck_if_handed(self) -> None:
        """The run's unsealed chunks changed hands (the node that held them died and another took the
        run over, or the depot restarted): chunks the old holder was said to hold may be gone. Ask
        about everything not known sealed, and send what is missing before the run is sealed without it."""
        if not self.handed:
            return
        self.handed = False
        start, end = self.state.confirmed_until, self.state.checked_until
        if end <= start:
            return
        entries = await asyncio.to_thread(self._entries, start, end)
        missing = await self._missing(entries)
        if missing:
            self.lanes.append(Lane(Priority.BACKFILL, entries=deque(missing), on_sent=self._count_resent))
            self.state.checked_until = missing[0].offset
            self.ctx.state.save_run(self.state)
            log.info("run %s: re-sending %d chunks its new holder lacks", self.run_id, len(missing))

    def _plan_lanes(self) -> None:
        """Live data from the file's end; a large gap behind it as backfill."""
        size = self._size()
        path = self._run().path
        if size - self.sent_until > BACKFILL_SPLIT_BYTES:
            self.lanes.append(
                Lane(Priority.BACKFILL, HotIndexTail(path, self.sent_until), end=size, on_sent=self._count_backfill)
            )
            self.lanes.append(Lane(Priority.LIVE, HotIndexTail(path, size), on_sent=self._advance))
        else:
            self.lanes.append(Lane(Priority.LIVE, HotIndexTail(path, self.sent_until), on_sent=self._advance))

    def add_pull(self, job: PullJob) -> None:
        self.pulls.append(job)
        self.wake.set()

    async def _plan_pulls(self) -> None:
        """A lane per pull not yet written and without one: the chunks of it the depot lacks."""
        laned = {id(lane.job) for lane in self.lanes if lane.job is not None}
        for job in list(self.pulls):  # (one the depot holds already is done and leaves the list)
            if job.written_at_check is None and id(job) not in laned:
                await self._queue_pull(job)

    async def _queue_pull(self, job: PullJob, missing: list[HotEntry] | None = None) -> None:
        """A lane of the chunks of `job` the depot lacks (`missing`, asked here when not given) that
        nothing else sends: chunks the live rules forward go with the run's own stream (live,
        backfill or a resend), and another pull's lane may hold some (two windows that overlap, a
        person's pull of a window a trigger sends). Each chunk goes once; the job is done once the
        depot holds all of its chunks, whoever sent them."""
        if missing is None:
            missing = await self._missing(job.entries, pulled=True)
        if not missing:
            await self._pull_done(job)  # the depot holds all of it already
            return
        queued = {e.meta.chunk_id for lane in self.lanes if lane.job is not None for e in lane.entries if e.meta}
        mine = [e for e in missing if e.meta is not None and e.meta.chunk_id not in queued and not self._forwarded(e)]
        if not mine:
            job.written_at_check = self.checks  # sent by others: asked about at a later check
            return
        self.lanes.append(Lane(job.priority, entries=deque(mine), on_sent=job.count, job=job))

    async def _pull_done(self, job: PullJob) -> None:
        if job in self.pulls:
            self.pulls.remove(job)
        await self._relearn_after_pull()
        job.done.set()

    async def _settle_pulls(self, checking: bool) -> None:
        """Written pulls the depot holds whole are done: asked every PULL_CONFIRM_S, so a trigger's
        window is known at the depot about a second after its last chunk, not at the next check.
        What one written before the previous check still lacks is sent again (at a check: sooner,
        it may be on its way)."""
        if not checking and time.monotonic() - self.last_confirm < PULL_CONFIRM_S:
            return
        self.last_confirm = time.monotonic()
        for job in [job for job in self.pulls if job.written_at_check is not None]:
            missing = await self._missing(job.entries, pulled=True)
            if not missing:
                await self._pull_done(job)
            elif checking and job.written_at_check is not None and job.written_at_check < self.checks - 1:
                job.written_at_check = None
                await self._queue_pull(job, missing)

    async def _relearn_after_pull(self) -> None:
        """A pull put chunks at the depot that were on the robot only: ask again what still is. Not
        while a backfill is under way (it counts what it passes, and would count those twice);
        the next start asks anyway."""
        if self._backfill_pending() is not None:
            return
        _, kept = await asyncio.to_thread(self._scan, self.sent_until)
        await self._learn_local_only(kept)

    def _has_work(self) -> bool:
        run = self._run()
        if run is None:
            return False
        size = self._size()
        return any(not lane.exhausted(size) for lane in self.lanes)

    async def _idle(self) -> None:
        """Nothing to send: wait for more data, or check on what the depot holds."""
        run = self._run()
        if run is None:
            return
        seen = run.changes.count
        await self._maybe_check()
        if self._size() <= self.sent_until and not self.wake.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._woken(run.changes, seen), self._wait_s(self.ctx.check_s))
        self.wake.clear()
        self.lanes.clear()

    async def _woken(self, changes: Any, seen: int) -> None:
        waiters = [asyncio.ensure_future(changes.wait(seen)), asyncio.ensure_future(self.wake.wait())]
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()

    async def _pump(self, call: Any, generation: int) -> None:
        """Send lane by lane, highest priority first, until all is sent and the run stays quiet."""
        while True:
            if self.wake.is_set():  # a pull (or a trigger's window) added while the run streams
                self.wake.clear()
                await self._plan_pulls()
            lane, entries = await asyncio.to_thread(self._next_batch)
            if lane is None:
                run = self._run()
                if run is None:
                    return
                if not self.ctx.spool.is_open(run) and time.monotonic() - self.last_append > LINGER_S:
                    return
                seen = run.changes.count
                if self._size() > self.sent_until or self.wake.is_set():
                    continue
                await self._maybe_check()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(
                        self._woken(run.changes, seen), self._wait_s(min(LINGER_S, self.ctx.check_s))
                    )
                continue
            self.last_append = time.monotonic()
            requests = await asyncio.to_thread(self._read, entries)
            for entry, request in zip(entries, requests, strict=True):
                await self._write(call, generation, request, lane.priority)
                if lane.on_sent is not None:
                    lane.on_sent(entry)
            await self._maybe_check()

    def _next_batch(self) -> tuple[Lane | None, list[HotEntry]]:
        """The next messages to send: of the highest-priority lane that has any (up to a read's worth)."""
        size = self._size()
        for lane in sorted(self.lanes, key=lambda lane: lane.priority):
            batch: list[HotEntry] = []
            nbytes = 0
            while nbytes < BATCH_BYTES:
                if not lane.entries and lane.tail is not None:
                    lane.entries.extend(lane.tail.read(size if lane.end is None else min(size, lane.end), limit=256))
                if not lane.entries:
                    break
                entry = lane.entries.popleft()
                if entry.kind == STORE_INFO and all(known.offset != entry.offset for known in self.store_infos):
                    self.store_infos.append(entry)  # a store that starts mid-run (a blueprint sent later)
                    batch.append(entry)
                    nbytes += entry.length
                    continue
                if entry.kind == STORE_INFO or (lane.job is None and not self._forwarded(entry)):
                    if lane.on_sent is not None:
                        lane.on_sent(entry)  # passed over, but counted as gone by
                    continue
                batch.append(entry)
                nbytes += entry.length
            if batch:
                return lane, batch
        for lane in self.lanes:
            if not lane.exhausted(size):
                continue
            if lane.job is not None and lane.job.written_at_check is None:
                lane.job.written_at_check = self.checks
            if lane.priority == Priority.BACKFILL and lane.tail is not None and lane.end is not None:
                self.sent_until = max(self.sent_until, lane.end)  # the gap is sent: live goes on from its end
        self.lanes = [lane for lane in self.lanes if lane.priority == Priority.LIVE or not lane.exhausted(size)]
        return None, []

    async def _write(self, call: Any, generation: int, request: bytes, priority: Priority) -> None:
        await self.ctx.bucket.acquire(len(request), priority)
        try:
            await asyncio.wait_for(call.write(request), self.ctx.stall_s)
        except TimeoutError:
            await self.ctx.link.replace_channel(generation)
            raise LinkDown(f"the depot took no data for {self.ctx.stall_s:g} s: the link is silent") from None
        except asyncio.CancelledError:
            if cancelled():
                raise
            raise LinkDown("the connection to the depot was dropped (silent link)") from None
        except Exception as exc:
            raise await stream_ended(call, exc) from exc
        self.ctx.counters["messages_sent"] += 1
        self.ctx.counters["bytes_sent"] += len(request)

    # --- bookkeeping ------------------------------------------------------------------------------

    def _advance(self, entry: HotEntry) -> None:
        self.sent_until = max(self.sent_until, entry.end)
        self._count_backfill(entry)

    def _count_backfill(self, entry: HotEntry) -> None:
        if entry.kind == CHUNK and entry.meta is not None and not self._forwarded(entry):
            self.state.local_only_chunks += 1
            self.state.local_only_bytes += entry.length
            self.local_only_entities.add(entry.meta.entity_path)

    def _count_resent(self, entry: HotEntry) -> None:
        self.ctx.counters["chunks_resent"] += 1
        self.ctx.counters["bytes_resent"] += entry.length

    def _checked(self, offset: int) -> None:
        if offset > self.state.checked_until:
            self.state.checked_until = offset
            self.ctx.state.save_run(self.state)

    def _backfill_pending(self) -> int | None:
        """The first offset a backfill lane has yet to send, if any."""
        starts = [
            lane.tail.position
            for lane in self.lanes
            if lane.priority == Priority.BACKFILL and lane.tail is not None and not lane.exhausted(self._size())
        ]
        starts += [lane.entries[0].offset for lane in self.lanes if lane.entries]
        return min(starts) if starts else None

    def _wait_s(self, idle_s: float) -> float:
        """How long to wait for more data: shorter while a written pull is to be confirmed."""
        return min(idle_s, PULL_CONFIRM_S) if any(job.written_at_check is not None for job in self.pulls) else idle_s

    async def _maybe_check(self) -> None:
        """Every `check_s`: ask about what was sent before the previous check, and, for a closed run
        all held, whether the depot sealed it (written pulls: see `_settle_pulls`)."""
        checking = time.monotonic() - self.last_check >= self.ctx.check_s
        if checking:
            self.last_check = time.monotonic()
            self.checks += 1
        await self._settle_pulls(checking)
        if not checking:
            return
        # what was written before this check (up to the first message a backfill has yet to send):
        # asked about at the next one, when it has surely reached the depot
        pending = self._backfill_pending()
        written = self.sent_until if pending is None else min(self.sent_until, pending)
        mark, self.check_mark = self.check_mark, written
        if mark is not None and mark > self.state.checked_until:
            entries = await asyncio.to_thread(self._entries, self.state.checked_until, mark)
            missing = await self._missing(entries)
            if missing:
                self.lanes.append(Lane(Priority.BACKFILL, entries=deque(missing), on_sent=self._count_resent))
                mark = missing[0].offset
            self._checked(mark)
        await self._recheck_if_handed()
        await self._maybe_confirm()

    async def _maybe_confirm(self) -> None:
        run = self._run()
        size = self._size()
        if run is None or self.ctx.spool.is_open(run) or self.state.checked_until < size or self.streaming:
            return
        entries = await asyncio.to_thread(self._entries, self.state.confirmed_until, size)
        chunks = [e for e in entries if e.kind == CHUNK and e.meta is not None and self._forwarded(e)]
        if chunks and self.state.depot_tier != SEALED:  # one chunk tells whether the depot sealed the run
            probe = await self.ctx.link.held(self.run_id, [chunks[-1].meta.chunk_id] if chunks[-1].meta else [])
            self.state.depot_tier = probe.tier
            if probe.tier != SEALED and probe.accepts_data:
                return
        held = await self.ctx.link.held(self.run_id, [e.meta.chunk_id for e in chunks if e.meta is not None])
        self.state.depot_tier = held.tier
        if held.missing and held.accepts_data:
            self.state.checked_until = min(e.offset for e in chunks if e.meta and e.meta.chunk_id in held.missing)
            self.ctx.state.save_run(self.state)
            return
        if (held.tier == SEALED and not held.unsealed) or not held.accepts_data:
            self.state.confirmed_until = size
            self.state.confirmed = True
            log.info("run %s: the depot holds it sealed (%s); the robot may delete its copy", self.run_id, held.tier)
        self.ctx.state.save_run(self.state)
