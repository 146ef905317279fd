"""A source of messages (one gRPC stream or one upload) and what it brought."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from services.cluster.ownership import Lease, Owner
from services.ingest.facts import SealedInfo
from services.rrd.frames import RerunVersion
from services.rrd.messages import Event, StoreInfoMessage, StoreKind

StoreKey = tuple[StoreKind, str]


@dataclass
class IngestReport:
    """What a source brought: the runs it touched and the chunks that were new or already held."""

    runs: list[str] = field(default_factory=list)
    dropped: list[str] = field(default_factory=list)  # runs refused part-way and dropped whole: not kept
    chunks_new: int = 0
    chunks_duplicate: int = 0
    bytes_duplicate: int = 0
    bytes_new: int = 0
    messages: int = 0
    catalog: str = "updated"  # "pending" when the catalog could not be written yet (the data is kept)

    def to_dict(self) -> dict[str, Any]:
        return {
            "runs": self.runs,
            "dropped": self.dropped,
            "chunks_new": self.chunks_new,
            "chunks_duplicate": self.chunks_duplicate,
            "bytes_duplicate": self.bytes_duplicate,
            "bytes_new": self.bytes_new,
            "messages": self.messages,
            "catalog": self.catalog,
        }


@dataclass
class Source:
    live: bool  # a gRPC stream (its runs are live while it lasts) rather than an upload
    robot: str | None = None  # the one robot whose runs it may write (a robot's ingest token), None: any
    version: RerunVersion | None = None
    run_of_store: dict[StoreKey, str] = field(default_factory=dict)
    recording_run: str | None = None  # where this source's blueprints go
    # Messages kept until they can be filed: blueprints before any recording (run None), and
    # messages of a run that is not hot yet (written when its first new chunk arrives).
    held: list[tuple[str | None, Event]] = field(default_factory=list)
    held_bytes: int = 0
    store_infos: dict[StoreKey, StoreInfoMessage] = field(default_factory=dict)
    sealed: dict[str, SealedInfo | None] = field(default_factory=dict)  # what `prepare` learnt per run
    attached: set[str] = field(default_factory=set)  # hot runs this source counts in their sources
    created: set[str] = field(default_factory=set)  # hot runs this source started
    report: IngestReport = field(default_factory=IngestReport)
    # (chunks, bytes) new per run: taken back out of `report` if the run is dropped
    new_of_run: dict[str, tuple[int, int]] = field(default_factory=dict)
    # Ownership (services/ingest/routing.py): runs routed so far, those this node owns, and the
    # owner this source is relayed to; `relayed_by`: the node that relayed this source here.
    routed: set[str] = field(default_factory=set)
    leases: dict[str, Lease] = field(default_factory=dict)
    relay_to: Owner | None = None
    relayed_by: str | None = None
