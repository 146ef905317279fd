"""Chunk keys and FetchChunks: every chunk of a run comes back as the bytes its recording stores
(hot file or sealed object), read by range, a few per response; keys that are not ours, runs that
do not exist, places that are no chunk, are refused with a status, never a crash."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import grpc
import pyarrow as pa
import pytest

from catalog import queries
from catalog.db import session_scope
from services.redap import chunks
from services.redap.dataframe import dataframe_part
from services.redap.keys import chunk_key, parse_chunk_key
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.retention import archive
from services.retention.service import promote_now
from services.rrd import iter_events
from services.rrd.chunk import chunk_meta, read_chunk
from services.rrd.frames import MESSAGE_HEADER_SIZE
from services.rrd.manifest import read_manifest
from services.rrd.messages import ArrowMessage, tuid_bytes
from services.rrd.pb import common_pb2
from services.sealed.tiers import Tiers
from services.sealed.write import RECORDING
from tests.services.redap.catalog_node import BigRedap, catalog_server, count_reads, entry_of
from tests.services.redap.client import Redap
from tests.services.retention import conftest as retention
from tests.services.retention.conftest import Node, NodeFactory
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk
tiers, make_node = retention.tiers, retention.make_node

SCENES = ("points", "blueprint", "large", "transforms")


# --- FetchChunks ---------------------------------------------------------------------------------


def recording_id(rec: Recording) -> str:
    return str(rec.recordings[0]["recording_id"])


def manifest_keys(client: Redap, entry: str, run_id: str) -> pa.Table:
    request = cloud_pb2.GetRrdManifestRequest(segment_id=common_pb2.SegmentId(id=run_id))
    answers = client.call("GetRrdManifest", request, entry=entry)
    return pa.concat_tables([read_manifest(a.rrd_manifest) for a in answers])


def fetch_request(keys: list[bytes], parts: int = 1, **columns: Any) -> cloud_pb2.FetchChunksRequest:
    """The viewer's request: chunk_id, chunk_is_static, chunk_byte_offset and chunk_key, in parts."""
    size = max(1, -(-len(keys) // parts))
    infos = []
    for start in range(0, max(len(keys), 1), size):
        table = pa.table({"chunk_key": pa.array(keys[start : start + size], pa.binary())})
        for name, values in columns.items():
            table = table.append_column(name, pa.array(values[start : start + size]))
        infos.append(dataframe_part(table))
    return cloud_pb2.FetchChunksRequest(chunk_infos=infos)


def raw_answers(client: BigRedap, request: cloud_pb2.FetchChunksRequest) -> list[bytes]:
    """The responses as sent (bytes), and checked to be FetchChunksResponse messages."""
    call = client.channel.unary_stream(
        "/rerun.cloud.v1alpha1.RerunCloudService/FetchChunks",
        request_serializer=cloud_pb2.FetchChunksRequest.SerializeToString,
        response_deserializer=None,
    )
    answers = list(call(request, metadata=client.metadata(), timeout=60))
    for answer in answers:
        cloud_pb2.FetchChunksResponse.FromString(answer)
    return answers


def stored(data: bytes, keys: list[bytes]) -> dict[bytes, bytes]:
    """chunk id -> the ArrowMsg bytes the file holds where each key points."""
    out = {}
    for key in keys:
        where = parse_chunk_key(key)
        assert where.chunk_id is not None
        out[where.chunk_id] = data[where.offset + MESSAGE_HEADER_SIZE : where.end]
    return out


def fetched(answers: list[bytes]) -> dict[bytes, bytes]:
    out = {}
    for answer in answers:
        for message in cloud_pb2.FetchChunksResponse.FromString(answer).chunks:
            raw = message.SerializeToString()
            out[tuid_bytes(message.chunk_id)] = raw
    return out


def sealed_bytes(node: Node, run_id: str) -> bytes:
    with session_scope(node.catalog) as session:
        life = queries.lifecycle(session, run_id)
        assert life is not None
        prefix = life.prefix
    return node.tiers.warm.get_range(f"{prefix}/{RECORDING}")


def uploaded(make_node: NodeFactory, tiers: Tiers, recs: list[Recording]) -> Node:
    node = make_node(tiers)
    for rec in recs:
        node.upload(rec.path)
    return node


def test_every_chunk_comes_back_as_stored_hot_and_sealed(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    recs = [recordings[s] for s in SCENES]
    node = uploaded(make_node, tiers, recs)
    # Small responses and reads, so a run takes many of each (the limits are what is checked).
    monkeypatch.setattr(chunks, "RESPONSE_BYTES", 64 * 1024)
    monkeypatch.setattr(chunks, "READ_BYTES", 256 * 1024)
    with catalog_server(node) as ours:
        for tier in ("hot", "sealed"):
            for rec in recs:
                run_id = recording_id(rec)
                if tier == "sealed":
                    promote_now(node.retention, run_id)
                data = node.ingest.runs[run_id].hot.path.read_bytes() if tier == "hot" else sealed_bytes(node, run_id)
                table = manifest_keys(ours, entry_of(node, rec.recordings[0]["application_id"]), run_id)
                keys = table.column("chunk_key").to_pylist()
                request = fetch_request(
                    keys,
                    parts=3,
                    chunk_id=table.column("chunk_id").to_pylist(),
                    chunk_is_static=table.column("chunk_is_static").to_pylist(),
                    chunk_byte_offset=table.column("chunk_byte_offset").to_pylist(),
                )
                answers = raw_answers(ours, request)
                got = fetched(answers)
                assert got == stored(data, keys), (tier, rec.name)  # byte for byte, every chunk
                total = sum(len(raw) for raw in got.values())
                assert len(answers) >= min(len(keys), total // (64 * 1024))  # a few per response, not all in one
                for answer in answers:
                    count = len(cloud_pb2.FetchChunksResponse.FromString(answer).chunks)
                    assert len(answer) <= 64 * 1024 + 64 or count == 1  # bounded, or one large chunk


def test_adjacent_chunks_are_read_together(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    rec = recordings["points"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    promote_now(node.retention, run_id)
    with catalog_server(node) as ours:
        table = manifest_keys(ours, entry_of(node, rec.recordings[0]["application_id"]), run_id)
        keys = table.column("chunk_key").to_pylist()
        reads = count_reads(monkeypatch, node.tiers.warm)
        got = fetched(raw_answers(ours, fetch_request(keys[::-1])))  # any order
    monkeypatch.undo()
    assert got == stored(sealed_bytes(node, run_id), keys)
    chunk_reads = [r for r in reads if r[0].endswith(RECORDING)]
    # The chunks sit one after the other (store infos between some): a handful of reads, not one each.
    assert len(chunk_reads) < len(keys) / 2, (len(chunk_reads), len(keys))


def test_a_key_from_the_hot_manifest_still_fetches_after_sealing(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording]
):
    rec = recordings["transforms"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    with catalog_server(node) as ours:
        table = manifest_keys(ours, entry_of(node, rec.recordings[0]["application_id"]), run_id)
        hot_keys = table.column("chunk_key").to_pylist()
        hot = fetched(raw_answers(ours, fetch_request(hot_keys)))
        promote_now(node.retention, run_id)  # the hot file is gone; the sealed recording has other offsets
        after = fetched(raw_answers(ours, fetch_request(hot_keys)))
    assert after == hot and len(after) == len(hot_keys)


def test_fetched_chunks_hold_what_rerun_server_sends(
    make_node: NodeFactory,
    tiers: Tiers,
    recordings: dict[str, Recording],
    reference_server: Callable[[dict[str, list[Recording]]], Redap],
):
    """Rerun's server decodes and re-encodes chunks; ours sends them as stored: the same chunks."""
    rec = recordings["points"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    reference = reference_server({"robot": [rec]})
    found = reference.call("FindEntries", cloud_pb2.FindEntriesRequest())
    entry = str(Tuid.from_proto(next(e.id.id for e in found.entries if e.name == "robot")))
    theirs_keys = manifest_keys(reference, entry, run_id).column("chunk_key").to_pylist()
    theirs = {}
    for answer in reference.call("FetchChunks", fetch_request(theirs_keys)):
        for message in answer.chunks:
            theirs[tuid_bytes(message.chunk_id)] = message
    with catalog_server(node) as ours:
        keys = manifest_keys(ours, entry_of(node, rec.recordings[0]["application_id"]), run_id)
        mine = fetched(raw_answers(ours, fetch_request(keys.column("chunk_key").to_pylist())))
    assert set(mine) == set(theirs)
    for chunk_id, raw in mine.items():
        ours_batch = read_chunk(_arrow(raw))
        theirs_batch = read_chunk(_arrow(theirs[chunk_id].SerializeToString()))
        assert ours_batch.equals(theirs_batch)


def _arrow(raw: bytes) -> ArrowMessage:
    from services.rrd.decoder import decode_message

    message = decode_message(2, raw)
    assert isinstance(message, ArrowMessage)
    chunk_meta(message)
    return message


def expect_error(call: Callable[[], Any], code: grpc.StatusCode, *words: str) -> None:
    with pytest.raises(grpc.RpcError) as info:
        call()
    error: Any = info.value
    assert error.code() == code, error.details()
    for word in words:
        assert word in error.details(), error.details()


def test_fetch_errors(make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording]):
    rec, cold = recordings["points"], recordings["transforms"]
    node = uploaded(make_node, tiers, [rec, cold])
    run_id, cold_id = recording_id(rec), recording_id(cold)
    with catalog_server(node) as ours:
        table = manifest_keys(ours, entry_of(node, rec.recordings[0]["application_id"]), run_id)
        cold_keys = manifest_keys(ours, entry_of(node, cold.recordings[0]["application_id"]), cold_id)
        promote_now(node.retention, cold_id)
        cold_key = cold_keys.column("chunk_key").to_pylist()[0]
        assert len(fetched(raw_answers(ours, fetch_request([cold_key])))) == 1  # warm: its place is kept a while
        archive.archive(cold_id, node.tiers, node.catalog, node.clock(), "test")
        key = table.column("chunk_key").to_pylist()[0]
        good = parse_chunk_key(key)
        assert good.chunk_id is not None
        hot_file = node.ingest.runs[run_id].hot.path
        store_info = next(e for e in iter_events(hot_file) if not isinstance(e, ArrowMessage) and hasattr(e, "raw"))

        def fetch(*keys: bytes) -> Callable[[], Any]:
            return lambda: raw_answers(ours, fetch_request(list(keys)))

        expect_error(fetch(b"garbage"), grpc.StatusCode.INVALID_ARGUMENT, "GetRrdManifest")
        expect_error(fetch(bytes(32)), grpc.StatusCode.INVALID_ARGUMENT)
        expect_error(fetch(chunk_key("no-such-run", 12, 100, good.chunk_id)), grpc.StatusCode.NOT_FOUND, "no-such-run")
        past_end = chunk_key(run_id, hot_file.stat().st_size, good.length, good.chunk_id)
        expect_error(fetch(past_end), grpc.StatusCode.INVALID_ARGUMENT, "past the end")
        shifted = chunk_key(run_id, good.offset + 1, good.length, good.chunk_id)
        # Not at a frame: found by its chunk id all the same (the run holds it).
        assert set(fetched(raw_answers(ours, fetch_request([shifted])))) == {good.chunk_id}
        unknown = chunk_key(run_id, good.offset + 1, good.length, bytes(16))
        expect_error(fetch(unknown), grpc.StatusCode.NOT_FOUND, "GetRrdManifest")
        at_store_info = chunk_key(run_id, store_info.offset, MESSAGE_HEADER_SIZE + len(store_info.raw), bytes(16))
        expect_error(fetch(at_store_info), grpc.StatusCode.NOT_FOUND)
        # Archived since: the kept place is not trusted, the catalog is asked again.
        expect_error(fetch(cold_key), grpc.StatusCode.FAILED_PRECONDITION, "fleet runs restore", cold_id)
        # One bad key fails the request before anything is sent.
        expect_error(fetch(key, b"garbage"), grpc.StatusCode.INVALID_ARGUMENT)
        no_keys = cloud_pb2.FetchChunksRequest(chunk_infos=[dataframe_part(pa.table({"chunk_id": [b"x"]}))])
        expect_error(lambda: raw_answers(ours, no_keys), grpc.StatusCode.INVALID_ARGUMENT, "chunk_key")
        bad_part = cloud_pb2.FetchChunksRequest(chunk_infos=[common_pb2.DataframePart(payload=b"not arrow")])
        expect_error(lambda: raw_answers(ours, bad_part), grpc.StatusCode.INVALID_ARGUMENT)
        # And the server goes on serving.
        assert set(fetched(raw_answers(ours, fetch_request([key])))) == {good.chunk_id}
        assert raw_answers(ours, cloud_pb2.FetchChunksRequest()) == []


def test_the_arrow_msg_is_not_parsed_again(monkeypatch: pytest.MonkeyPatch):
    """The registered FetchChunks handler hands gRPC bytes: no ArrowMsg is parsed or serialized."""
    from services.redap import grpc_handler

    taken: dict[str, Any] = {}

    class Server:
        def add_generic_rpc_handlers(self, handlers: Any) -> None:
            pass

        def add_registered_method_handlers(self, service: str, handlers: dict[str, Any]) -> None:
            taken.update(handlers)

    grpc_handler.add_to_server(Server(), grpc_handler.CatalogServer(None, None))  # type: ignore[arg-type]
    assert taken["FetchChunks"].response_serializer is None
    assert taken["FetchChunks"].request_deserializer is None  # parsed by the handler once the token is checked
    assert taken["GetRrdManifest"].response_serializer == cloud_pb2.GetRrdManifestResponse.SerializeToString
