"""A source of messages (one gRPC stream or one upload) and what it brought."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from services.cluster.ownership import Lease, Owner
from services.facts.sealed import SealedInfo
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
    warnings: list[str] = field(default_factory=list)  # what the uploader should know (kept data is fine)

    def drop_run(self, run_id: str) -> None:
        """Report `run_id` as dropped, not kept."""
        self.runs = [r for r in self.runs if r != run_id]
        if run_id not in self.dropped:
            self.dropped.append(run_id)

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
            "warnings": self.warnings,
        }


@dataclass
class RunOverlap:
    """Of one run a source fed: whether the run held chunks before, and how many of the source's
    recording chunks were new to it or already held."""

    held_before: bool
    new: int = 0
    duplicate: int = 0

    def disjoint(self) -> bool:
        """Chunks added to a run that had data, none in common with it: most likely a second
        recording of the same run (an SDK 0.23 file saved beside its live stream has other chunk ids)."""
        return self.held_before and self.new > 0 and self.duplicate == 0


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
    overlap: dict[str, RunOverlap] = field(default_factory=dict)  # per run: chunks in common with it

    def count_chunk(self, run_id: str, held_before: Callable[[], bool], *, duplicate: bool) -> None:
        """Count one recording chunk of `run_id` (`held_before`: asked at the run's first chunk)."""
        overlap = self.overlap.get(run_id)
        if overlap is None:
            overlap = self.overlap[run_id] = RunOverlap(held_before())
        if duplicate:
            overlap.duplicate += 1
        else:
            overlap.new += 1

    def overlap_warnings(self) -> list[str]:
        """An upload that doubled a run: it shares no chunk with data the run already held."""
        out = []
        for run_id, overlap in self.overlap.items():
            if not overlap.disjoint():
                continue
            info = self.store_infos.get((StoreKind.RECORDING, run_id))
            version = info.sdk_version if info is not None else None
            by = f" (written by rerun-sdk {version.major}.{version.minor})" if version is not None else ""
            out.append(
                f"run {run_id!r} already held data of this recording id, and none of this file's "
                f"{overlap.new} chunks{by} were among it: the file is likely a second recording of the "
                "same run (rerun-sdk 0.23 has no set_sinks, and a file it saves beside a live stream gets "
                "other chunk ids), so the run now holds that data twice"
            )
        return out
