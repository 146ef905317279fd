"""What ingest calls as a run's chunks arrive, typed here, below ingest (the corpus's live rules
implement it; `IngestService(..., observer=...)` takes one)."""

from __future__ import annotations

from typing import Protocol

from services.rrd.chunk import ChunkMeta
from services.rrd.messages import ArrowMessage


class ChunkObserver(Protocol):
    """Sees the recording chunks of hot runs (not property chunks). `wants` is asked for each new
    chunk, so it must be cheap (a dict lookup: `spec.RuleSet.names_entity`); `chunk` is called only
    for a chunk it wants, on ingest's thread, so it must not block (hand the chunk on and return)."""

    def wants(self, entity_path: str) -> bool: ...

    def chunk(self, run_id: str, robot_id: str, msg: ArrowMessage, meta: ChunkMeta) -> None: ...

    def started(self, run_id: str, robot_id: str) -> None:
        """Ingest created the run's hot file here, before its first chunk: there is nothing of it to read."""
