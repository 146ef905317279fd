"""An RRD file on this machine opened as an indexed recording (an episode the command line
downloaded to export it): its messages scanned once for their chunk index (up to its end marker,
before the footer), then read back by range."""

from __future__ import annotations

import os
from pathlib import Path

from services.rrd.chunk import chunk_meta
from services.rrd.chunk_index import BLUEPRINT_ACTIVATION, STORE_INFO, IndexRow, chunk_row, store_kind_name
from services.rrd.decoder import decode_message
from services.rrd.frames import MESSAGE_HEADER_SIZE, STREAM_HEADER_SIZE, MessageKind, decode_message_header
from services.rrd.messages import ArrowMessage, StoreInfoMessage
from services.runs.indexed import IndexedRecording, ReadRange


def open_rrd_file(path: Path) -> IndexedRecording:
    """`path` read by range, its messages indexed (close it when done)."""
    fd = os.open(path, os.O_RDONLY)
    size = os.fstat(fd).st_size

    def read(offset: int, length: int) -> bytes:
        return os.pread(fd, length, offset)

    try:
        rows = _index(read, size)
    except BaseException:
        os.close(fd)
        raise
    return IndexedRecording(read, size, lambda: rows, close=lambda: os.close(fd))


def _index(read: ReadRange, size: int) -> list[IndexRow]:
    rows: list[IndexRow] = []
    offset = STREAM_HEADER_SIZE
    while offset + MESSAGE_HEADER_SIZE <= size:
        kind, length = decode_message_header(read(offset, MESSAGE_HEADER_SIZE))
        if kind == MessageKind.END or offset + MESSAGE_HEADER_SIZE + length > size:
            break
        frame = MESSAGE_HEADER_SIZE + length
        message = decode_message(kind, read(offset + MESSAGE_HEADER_SIZE, length), offset)
        if isinstance(message, ArrowMessage):
            rows.append(chunk_row(store_kind_name(message.store_id.kind), offset, frame, chunk_meta(message)))
        elif isinstance(message, StoreInfoMessage):
            rows.append(IndexRow(STORE_INFO, store_kind_name(message.store_id.kind), offset, frame))
        else:
            rows.append(IndexRow(BLUEPRINT_ACTIVATION, "blueprint", offset, frame))
        offset += frame
    return rows
