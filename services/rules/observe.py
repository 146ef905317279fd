"""What ingest tells of the chunks it files: the one way rules see a hot run as it streams."""

from __future__ import annotations

from typing import Protocol

from services.rrd.chunk import ChunkMeta
from services.rrd.messages import ArrowMessage


class ChunkObserver(Protocol):
    def wants(self, entity_path: str) -> bool: ...

    def chunk(self, run_id: str, robot_id: str, msg: ArrowMessage, meta: ChunkMeta) -> None: ...
