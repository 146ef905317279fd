"""RRD stream writer: header, messages passed through byte for byte, End and a footer.

The footer holds one RRD manifest per store that has chunks, with offsets counted from the
start of this stream, so footer readers (`rerun rrd verify`, the catalog server) can seek.
"""

from __future__ import annotations

import dataclasses
from typing import BinaryIO

from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.frames import (
    HEADER_COMPRESSION_LZ4,
    MESSAGE_HEADER_SIZE,
    MessageKind,
    RerunVersion,
    StreamHeader,
    encode_message_header,
    encode_stream_footer,
)
from services.rrd.manifest import ManifestEntry, build_manifest
from services.rrd.messages import ArrowMessage, Buffer, EndMessage, Message, StoreId, tuid_proto
from services.rrd.pb import log_msg_pb2
from services.rrd.store_ids import StoreIdResolver


def with_chunk_fields(raw: Buffer, meta: ChunkMeta) -> bytes:
    """An ArrowMsg of SDK 0.23 or older (chunk id only inside the Arrow payload) with the
    `chunk_id` and `is_static` fields newer SDKs send, which footer readers seek by (`rerun rrd
    verify` requires them). The fields are appended: protobuf merges them into the message as
    sent, and the payload bytes stay untouched."""
    fields = log_msg_pb2.ArrowMsg(chunk_id=tuid_proto(meta.chunk_id), is_static=meta.is_static)
    return bytes(raw) + fields.SerializeToString()


class RrdEncoder:
    """Writes one RRD stream to `sink` (any binary file-like; it need not be seekable)."""

    def __init__(
        self,
        sink: BinaryIO,
        version: RerunVersion,
        *,
        compression: int = HEADER_COMPRESSION_LZ4,
        write_footer: bool = True,
    ) -> None:
        self._sink = sink
        self._write_footer = write_footer
        self._entries: dict[StoreId, list[ManifestEntry]] = {}
        self._finished = False
        # Manifests are keyed by complete store ids, also for chunks of pre-0.25 SDKs (whose
        # ArrowMsg names no application id) when the caller did not complete them.
        self._store_ids = StoreIdResolver()
        header = StreamHeader(version, compression).encode()
        sink.write(header)
        self.position = len(header)  # bytes written so far; offsets are relative to this stream

    def write(self, msg: Message, meta: ChunkMeta | None = None) -> None:
        """Append a message read by the decoder. End messages are skipped: `finish()` writes
        this stream's own. `meta` spares re-reading an Arrow chunk when the caller has it."""
        if isinstance(msg, EndMessage):
            return
        msg = self._store_ids.complete(msg)
        if isinstance(msg, ArrowMessage):
            self.write_arrow(msg, meta)
            return
        self._frame(msg.kind, msg.raw)

    def write_arrow(self, msg: ArrowMessage, meta: ChunkMeta | None = None) -> None:
        raw = msg.raw
        if self._write_footer:
            meta = meta or chunk_meta(msg)
            if msg.chunk_id is None:
                raw = with_chunk_fields(raw, meta)
                meta = dataclasses.replace(meta, byte_size=len(raw))
            entry = ManifestEntry(meta, self.position + MESSAGE_HEADER_SIZE)
            self._entries.setdefault(self._store_ids.resolve(msg.store_id), []).append(entry)
        self._frame(MessageKind.ARROW_MSG, raw)

    def write_raw(
        self, kind: MessageKind, raw: Buffer, *, store_id: StoreId | None = None, meta: ChunkMeta | None = None
    ) -> None:
        """Append a message given as protobuf bytes (for example from a gRPC LogMsg)."""
        if kind == MessageKind.ARROW_MSG and self._write_footer:
            if store_id is None or meta is None:
                raise ValueError("an Arrow message needs its store id and chunk metadata for the footer")
            self._entries.setdefault(self._store_ids.resolve(store_id), []).append(
                ManifestEntry(meta, self.position + MESSAGE_HEADER_SIZE)
            )
        self._frame(kind, raw)

    def finish(self) -> None:
        """Write End (with the footer) and the stream trailer. Idempotent."""
        if self._finished:
            return
        if not self._write_footer:
            self._frame(MessageKind.END, b"")
            self._finished = True
            return
        footer = log_msg_pb2.RrdFooter(
            manifests=[build_manifest(store, entries) for store, entries in self._entries.items()]
        )
        payload = footer.SerializeToString()
        footer_start = self.position + MESSAGE_HEADER_SIZE
        self._frame(MessageKind.END, payload)
        self._finished = True
        trailer = encode_stream_footer(footer_start, payload)
        self._sink.write(trailer)
        self.position += len(trailer)

    def _frame(self, kind: int, raw: Buffer) -> None:
        if self._finished:
            raise ValueError("stream already finished")
        self._sink.write(encode_message_header(kind, len(raw)))
        self._sink.write(raw)
        self.position += MESSAGE_HEADER_SIZE + len(raw)
