"""Opening a segment: its RRD manifest (the sealed footer's, or the hot run's chunk index) with
chunk keys, and its assets. A snapshot's segment (an episode, `snapshots.py`) is its run's manifest
cut to the episode's chunks: its rows, and the Sorbet schema's columns of the entities they hold;
its store id and chunk keys name the segment, so the chunks fetched are the segment's.

Answered as Rerun's own server answers a recording with a footer: the footer manifest's columns
(every field nullable, as it serves them) plus `chunk_key` (binary), the footer's Sorbet schema
with `sorbet:version` in its metadata, and the schema's hash as Rerun computes it. A sealed run's footer is read
from the end of its `recording.rrd` by byte range; a hot run's manifest is built from its chunk
index with the same builder that writes footers at sealing, so a run looks the same before and
after. `generate_direct_urls` is not honoured (the protocol lets a server inline the manifest
whatever the client asks, and Rerun's server does the same).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import lz4.block
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from google.protobuf.message import DecodeError

from catalog.datasets import chunk_ids_of
from catalog.db import session_scope
from core.errors import InternalError, InvalidArgumentError, NotFoundError, UnavailableError
from services.auth.scopes import Principal
from services.hot.read import HotRecording
from services.redap import snapshots
from services.redap.dataframe import ipc_stream
from services.redap.datasets import segment_run
from services.redap.depot import Depot
from services.redap.keys import EPISODE_SEPARATOR, episode_chunk_id, key_column
from services.redap.pb import cloud_pb2
from services.redap.recordings import open_recording
from services.redap.schema import narrowed
from services.redap.snapshots import SnapshotVersion, find_dataset
from services.redap.tuid import Tuid
from services.rrd.chunk_index import STORE_INFO
from services.rrd.decoder import decode_message
from services.rrd.frames import (
    FOOTER_ENTRY_SIZE,
    FOOTER_FIXED_SIZE,
    FOOTER_MAGIC,
    MESSAGE_HEADER_SIZE,
    MessageKind,
    decode_footer_entry,
    footer_crc,
)
from services.rrd.manifest import ManifestEntry, build_manifest, read_manifest, read_sorbet_schema, schema_sha256
from services.rrd.messages import StoreId, StoreInfoMessage, StoreKind
from services.rrd.migrations import CURRENT_VERSION, VERSION_KEY
from services.rrd.pb import common_pb2, log_msg_pb2
from services.storage.objectstore import ObjectStore

_TRAILER = FOOTER_ENTRY_SIZE + FOOTER_FIXED_SIZE
SORBET_VERSION = ".".join(map(str, CURRENT_VERSION)).encode()
# A manifest larger than this (Arrow IPC) goes in several parts of whole rows, which clients merge:
# every part carries the same schemas.
PART_BYTES = 16 * 1024 * 1024


@dataclass(frozen=True)
class Segment:
    """What a segment reads: a run, or of a run a snapshot episode's chunks."""

    run_id: str
    segment_id: str
    chunk_ids: frozenset[bytes] | None = None


def rrd_manifest(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.GetRrdManifestRequest
) -> Iterator[cloud_pb2.GetRrdManifestResponse]:
    segment = find_segment(depot, entry, request.segment_id.id if request.HasField("segment_id") else "")
    run_id = segment.run_id
    for _ in range(2):  # a hot run sealed (its file removed) while its manifest was read is read again
        recording = open_recording(depot, run_id)
        try:
            if recording.hot is None:
                assert recording.store is not None
                found = sealed_manifest(run_id, recording.store, recording.key, recording.size)
                return served_manifest(segment.segment_id, found, segment.chunk_ids)
            manifest = hot_manifest(run_id, recording.hot)
            if recording.hot.path.exists():
                return served_manifest(segment.segment_id, manifest, segment.chunk_ids)
        finally:
            recording.close()
    raise UnavailableError(f"run {run_id!r} is being sealed right now: try again in a moment")


def assets(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.GetAssetsForSegmentRequest
) -> Iterator[cloud_pb2.GetAssetsForSegmentResponse]:
    """No asset dataset: an empty stream, which Rerun's clients read as "this dataset has no
    assets" (one response naming an asset dataset is what a server with assets sends)."""
    if request.HasField("segment_id") and request.segment_id.id:
        find_segment(depot, entry, request.segment_id.id)
    else:
        with session_scope(depot.catalog) as session:
            find_dataset(session, entry)
    return iter(())


def find_segment(depot: Depot, entry: Tuid, segment_id: str) -> Segment:
    """What a segment of the dataset reads (NOT_FOUND if it is none of the dataset's, or if a
    snapshot's episode reads a run deleted since, saying so)."""
    if not segment_id:
        raise InvalidArgumentError(
            "name the segment: segment_id is a run id (of a snapshot: an episode's), as the segment table lists them"
        )
    with session_scope(depot.catalog) as session:
        dataset = find_dataset(session, entry)
        if isinstance(dataset, SnapshotVersion):
            episode = snapshots.episode_of(session, dataset, segment_id)
            missing = snapshots.missing_why(session, dataset, episode)
            if missing is not None:
                raise NotFoundError(missing)
            return Segment(episode.run_id, segment_id, frozenset(chunk_ids_of(episode)))
        run_id: str = segment_run(session, dataset, segment_id).id
    return Segment(run_id, run_id)


# --- the manifests --------------------------------------------------------------------------------


def sealed_manifest(run_id: str, store: ObjectStore, key: str, size: int) -> log_msg_pb2.RrdManifest:
    """The recording's manifest from the footer of its sealed `recording.rrd`: the trailer, then
    the footer, by range (two reads, however large the run)."""
    damaged = InternalError(f"the sealed recording of run {run_id!r} has no usable footer: seal it again")
    if size < _TRAILER:
        raise damaged
    trailer = store.get_range(key, size - _TRAILER, _TRAILER)
    if trailer[FOOTER_ENTRY_SIZE : FOOTER_ENTRY_SIZE + len(FOOTER_MAGIC)] != FOOTER_MAGIC:
        raise damaged
    start, length, crc = decode_footer_entry(trailer)  # stream-relative: the sealed stream starts at 0
    if start + length + _TRAILER != size:
        raise damaged
    payload = store.get_range(key, start, length)
    if footer_crc(payload) != crc:
        raise damaged
    try:
        footer = log_msg_pb2.RrdFooter.FromString(payload)
    except DecodeError as exc:
        raise damaged from exc
    recordings = [m for m in footer.manifests if m.store_id.kind == common_pb2.STORE_KIND_RECORDING]
    if not recordings:  # a run of nothing but a blueprint and properties held back: no chunks
        return build_manifest(StoreId(StoreKind.RECORDING, "", run_id), [])
    return next((m for m in recordings if m.store_id.recording_id == run_id), recordings[0])


def hot_manifest(run_id: str, hot: HotRecording) -> log_msg_pb2.RrdManifest:
    """The manifest of a hot run's recording store, from its chunk index, as sealing will write it."""
    index = hot.chunk_index()
    entries = [
        ManifestEntry(e.meta, e.offset + MESSAGE_HEADER_SIZE)
        for e in index.entries
        if e.meta is not None and e.store_kind == "recording"
    ]
    store = StoreId(StoreKind.RECORDING, "", run_id)
    info = next((e for e in index.entries if e.kind == STORE_INFO and e.store_kind == "recording"), None)
    if info is not None:
        with open(hot.path, "rb") as fh:
            fh.seek(info.offset + MESSAGE_HEADER_SIZE)
            message = decode_message(MessageKind.SET_STORE_INFO, fh.read(info.length - MESSAGE_HEADER_SIZE))
        if isinstance(message, StoreInfoMessage):
            store = message.store_id
    return build_manifest(store, entries)


def served_manifest(
    segment_id: str, manifest: log_msg_pb2.RrdManifest, chunk_ids: frozenset[bytes] | None = None
) -> Iterator[cloud_pb2.GetRrdManifestResponse]:
    """The manifest as clients get it: nullable columns plus `chunk_key`, in parts of whole rows;
    with `chunk_ids`, only those chunks (a snapshot's episode), its store id naming the segment."""
    table = read_manifest(manifest)
    sorbet = read_sorbet_schema(manifest)
    store_id = manifest.store_id
    if chunk_ids is not None:
        ids = table.column("chunk_id")
        table = table.filter(pc.is_in(ids, value_set=pa.array(sorted(chunk_ids), ids.type)))
        entities = set(table.column("chunk_entity_path").to_pylist())
        sorbet = narrowed(sorbet, entities, {f.name for f in sorbet})
        store_id = common_pb2.StoreId()
        store_id.CopyFrom(manifest.store_id)
        store_id.recording_id = segment_id
    table = table.combine_chunks()
    # The manifest's offsets and sizes are the ArrowMsg payload's: a key names the whole frame.
    keys = key_column(
        segment_id,
        _ints(table.column("chunk_byte_offset")) - MESSAGE_HEADER_SIZE,
        _ints(table.column("chunk_byte_size")) + MESSAGE_HEADER_SIZE,
        table.column("chunk_id"),
    )
    if EPISODE_SEPARATOR in segment_id:  # a window's chunks go by ids of its own (chunks.py)
        ids = table.column("chunk_id").to_pylist()
        shown = pa.array([episode_chunk_id(segment_id, i) for i in ids], table.schema.field("chunk_id").type)
        table = table.set_column(table.schema.get_field_index("chunk_id"), table.schema.field("chunk_id"), shown)
    fields = [f.with_nullable(True) for f in table.schema] + [pa.field("chunk_key", pa.binary())]
    columns = [column.chunk(0) if column.num_chunks else pa.array([], column.type) for column in table.columns]
    served = pa.RecordBatch.from_arrays([*columns, keys], schema=pa.schema(fields))
    # Hashed again as Rerun hashes it: footers sealed before the depot did so carry another hash.
    sha256 = schema_sha256(sorbet)
    sorbet = sorbet.with_metadata({**(sorbet.metadata or {}), VERSION_KEY: SORBET_VERSION})
    sorbet_proto = common_pb2.Schema(arrow_schema=sorbet.serialize().to_pybytes())
    for part in _parts(served):
        yield cloud_pb2.GetRrdManifestResponse(
            rrd_manifest=log_msg_pb2.RrdManifest(
                store_id=store_id,
                sorbet_schema=sorbet_proto,
                sorbet_schema_sha256=sha256,
                data=part,
            )
        )


def _ints(column: pa.ChunkedArray) -> Any:
    """An offset or size column as a numpy array of int64 (a footer's columns hold no null there)."""
    return column.to_numpy().astype(np.int64)


def _parts(batch: pa.RecordBatch) -> Iterator[common_pb2.DataframePart]:
    """One record batch per part (what Rerun's clients read of a part)."""
    whole = ipc_stream(batch)
    count = max(1, math.ceil(len(whole) / PART_BYTES))
    if count == 1:
        yield _lz4_part(whole)
        return
    rows = math.ceil(batch.num_rows / count)
    for start in range(0, batch.num_rows, rows):
        yield _lz4_part(ipc_stream(batch.slice(start, rows)))


def _lz4_part(ipc: pa.Buffer) -> common_pb2.DataframePart:
    return common_pb2.DataframePart(
        encoder_version=common_pb2.ENCODER_VERSION_V0,
        payload=lz4.block.compress(ipc, store_size=False),
        compression=common_pb2.COMPRESSION_LZ4,
        uncompressed_size=len(ipc),
    )
