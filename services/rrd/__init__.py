"""Rerun RRD wire codec: read and write RRD streams exactly as the Rerun SDK and viewer do.

Entry points: `RrdDecoder` / `iter_events` (read), `RrdEncoder` (write), `chunk_meta` (index a chunk).
"""

from services.rrd.chunk import ChunkMeta, chunk_meta, read_chunk
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE, RrdDecoder, iter_events
from services.rrd.encoder import RrdEncoder
from services.rrd.frames import MessageKind, RerunVersion
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    EndMessage,
    StoreId,
    StoreInfoMessage,
    StoreKind,
    StreamFooter,
    StreamStart,
)

__all__ = [
    "DEFAULT_MAX_MESSAGE_SIZE",
    "ArrowMessage",
    "BlueprintActivationMessage",
    "ChunkMeta",
    "EndMessage",
    "MessageKind",
    "RerunVersion",
    "RrdDecoder",
    "RrdEncoder",
    "StoreId",
    "StoreInfoMessage",
    "StoreKind",
    "StreamFooter",
    "StreamStart",
    "chunk_meta",
    "iter_events",
    "read_chunk",
]
