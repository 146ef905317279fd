"""A run in this node's hot tier as ingest holds it (`IngestRun`): its facts (`facts.run.RunFacts`)
plus its file, its streams and its hand-over to the warm tier (or to another node). Other services
see it as a `view.HotRunView`, a frozen copy: only ingest writes a run."""

from __future__ import annotations

import datetime as dt
import threading

from services.cluster.ownership import Lease
from services.facts.identity import DEFAULT_SECRETS, SecretFields
from services.facts.run import RunFacts
from services.facts.sealed import SealedInfo
from services.hot.store import HotRun


class IngestRun(RunFacts):
    """A run in this node's hot tier as ingest holds it: its facts, its file (`HotRun`), whether
    streams feed it, its lease, and its hand-over. Only ingest keeps these in `IngestService.runs`
    and writes them; other services get `HotRunView`s (`hot_run`, `hot_runs`, `closed_runs`)."""

    def __init__(self, hot: HotRun, now: dt.datetime, secret_fields: SecretFields = DEFAULT_SECRETS) -> None:
        super().__init__(hot.run_id, now, secret_fields)
        self.hot = hot
        self.leaving = threading.Lock()  # held by ingest per write, and by `IngestService.hand_over`
        self.handed_over = False  # left this node's hot tier: new data for this run starts a new hot run
        self.sealed_to: SealedInfo | None = None  # where promotion put it (for data that follows)
        self.adds_to: SealedInfo | None = None  # this hot run adds chunks to a run sealed before
        self.lease: Lease | None = None  # this node owns the run (None: filed here, to hand over)
        self.catalog_failures = 0  # consecutive failed catalog writes of this run (one bad run waits alone)
        self.catalog_retry_at: dt.datetime | None = None

    def recording_bytes(self) -> int:
        return self.hot.size  # the hot file knows its size

    def holds(self, chunk_id: bytes) -> bool:
        """Whether this run already has the chunk: in its hot file, or sealed before."""
        return chunk_id in self.chunk_ids or (self.adds_to is not None and chunk_id in self.adds_to.chunk_ids)
