"""A hot run as services outside ingest see it (`HotRunView`): a frozen copy of what they read of an
`IngestRun`, so only ingest ever writes a run; and what a hand-over leaves to its caller (`HandedOver`).

Not among the modules compiled with mypyc (`services/compiled.py`): views are taken by readers and
the schedule, not per chunk, and `cached_property` needs an instance dict."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

from catalog.queries import RunRecord
from core.states import RunStatus
from services.cluster.ownership import Lease
from services.facts.sealed import SealedInfo
from services.hot.store import Changes
from services.ingest.run import IngestRun


@dataclass(frozen=True)
class HotRunView:
    """A hot run of this node as services outside ingest see it: its figures as they stood when
    ingest was asked. Ingest goes on writing the run; ask again for newer figures.

    Copying a run's chunk ids (a set as large as the run) for every run each time the schedule or a
    page lists the hot runs would cost more than the listing, so `chunk_ids` is copied when first
    read, `in_hot_file` asks the run without a copy, and `record` builds the catalog record when
    called. The live run stays behind them (`_run`: for ingest's own checks, never written here)."""

    run_id: str
    robot_id: str | None  # as its messages or its token named it (None: the depot's default robot)
    started_by: str | None  # the robot whose token started the hot file, if one did
    application_id: str
    status: RunStatus
    started_ns: int | None  # its start time, or else its first log_time (ns since the epoch)
    ended_at: dt.datetime | None
    last_data_at: dt.datetime
    sources: int  # streams and uploads feeding it (live or not)
    live_sources: int
    chunks: int  # chunks of its recording store
    size: int  # bytes of its hot file: what a reader reads of it, and what a hand-over checks
    path: Path  # its hot file
    changes: Changes  # notified when the file grows or the run ends
    lease: Lease | None  # this node owns the run (None: filed here, to hand over)
    adds_to: SealedInfo | None  # it adds chunks to a run sealed before
    _run: IngestRun = field(repr=False, compare=False)

    @property
    def directory(self) -> Path:
        """The run's hot folder (its file, its chunk index, and sealing's work while it is sealed)."""
        return self.path.parent

    @cached_property
    def chunk_ids(self) -> frozenset[bytes]:
        """The chunks in its hot file, copied when first read (one C-level call, which the GIL keeps
        whole while ingest adds to the set)."""
        return frozenset(self._run.chunk_ids)

    def in_hot_file(self, chunk_id: bytes) -> bool:
        """Whether its hot file holds the chunk now (a membership test: no copy of its chunk ids)."""
        return chunk_id in self._run.chunk_ids

    def record(self, default_robot: str) -> RunRecord:
        """Its catalog record as the catalog would file it now (`RunFacts.record`)."""
        return self._run.record(default_robot)


def view_of(run: IngestRun) -> HotRunView:
    """`run` as other services see it now: a few attribute reads (its chunk ids and catalog record
    are copied only when a reader asks for them)."""
    summary = run.summary
    return HotRunView(
        run_id=run.run_id,
        robot_id=run.robot_id,
        started_by=run.hot.robot,
        application_id=run.application_id,
        status=run.status,
        started_ns=run.start_time_ns or run.first_log_time_ns,
        ended_at=run.ended_at,
        last_data_at=run.last_data_at,
        sources=run.sources,
        live_sources=run.live_sources,
        chunks=summary.chunks if summary is not None else 0,
        size=run.hot.size,
        path=run.hot.path,
        changes=run.hot.changes,
        lease=run.lease,
        adds_to=run.adds_to,
        _run=run,
    )


@dataclass(frozen=True)
class HandedOver:
    """What `IngestService.hand_over` leaves to its caller once the run has left the hot tier."""

    folder: Path  # the run's hot folder, set aside: the caller removes it (outside the run's lock)
    lease: Lease | None  # the lease the run held as it left (promotion's drop of a copy gives it up)
