"""The layout cache keys a chunk schema without what differs from chunk to chunk: the chunk id, and
the times the SDK stamps on every chunk it sends over gRPC (`rerun:timestamp_sdk_ipc_encoded`,
`rerun:timestamp_sdk_grpc_sink`, as rerun-sdk 0.41 writes them: "SECONDS.NANOSECONDS"). Keyed with
them, a streamed run cached and indexed one layout per chunk: memory grew with every chunk."""

from __future__ import annotations

import pyarrow as pa
import pytest

from services.rrd import layout
from services.rrd.layout import LayoutCache, _cut, split_ipc, volatile_spans

STAMP = "rerun:timestamp_sdk_ipc_encoded"
SENT = "rerun:timestamp_sdk_grpc_sink"


def schema_message(stamp: str | None, entity: str = "/robot/speed", chunk_id: str = "chunk_1") -> bytes:
    metadata = {"rerun:entity_path": entity, "sorbet:version": "0.1.3", "rerun:id": chunk_id}
    if stamp is not None:
        metadata[SENT] = stamp[:-1] + "0"
        metadata[STAMP] = stamp
    fields = [
        pa.field("rerun.controls.RowId", pa.binary(16), metadata={"rerun:kind": "control"}),
        pa.field("frame", pa.int64(), metadata={"rerun:kind": "index", "rerun:index_name": "frame"}),
        pa.field(
            "Scalars:scalars",
            pa.list_(pa.float64()),
            metadata={"rerun:kind": "data", "rerun:component": "Scalars:scalars", "rerun:archetype": "Scalars"},
        ),
    ]
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, pa.schema(fields, metadata=metadata)):
        pass
    split = split_ipc(sink.getvalue().to_pybytes())
    assert split is not None
    return split[0]


def _without_volatile_values(message: bytes) -> bytes:
    """The layout cache's key of `message` before the chunk id is blanked."""
    return _cut(message, volatile_spans(message))


def test_the_encode_stamp_is_cut_from_the_key_and_nothing_else():
    a, b = schema_message("1795409270.262298820"), schema_message("1795409271.004400113")
    assert a != b and _without_volatile_values(a) == _without_volatile_values(b)
    assert b"1795409270" not in _without_volatile_values(a)
    assert _without_volatile_values(schema_message(None)) == schema_message(None)  # nothing to cut
    other = schema_message("1795409270.262298820", "/robot/battery")
    assert _without_volatile_values(other) != _without_volatile_values(a)  # the rest still tells schemas apart


def test_chunks_stamped_apart_share_one_layout():
    cache = LayoutCache()
    first = cache.get(schema_message("1795409270.262298820"), b"", 0)
    assert cache.get(schema_message("1795409299.000000001"), b"", 0) is first
    assert cache.get(schema_message("1795409270.262298820", "/robot/battery"), b"", 0) is not first


def test_an_unreadable_message_is_its_own_key():
    garbage = b"\x08\x00\x00\x00" + STAMP.encode() + b"\xff" * 7
    assert _without_volatile_values(garbage) == garbage


def test_chunks_of_one_schema_with_their_own_ids_and_stamps_share_one_layout():
    """As a streamed run's chunks come: both the chunk id and the stamps differ (the stamps are cut
    first, where the flatbuffers say they are; then the id)."""
    cache = LayoutCache()
    ids = ("chunk_18EA9338064ABCF93036b01b8886355e", "chunk_18EA93380660508A3036b01b88863563")
    stamps = ("1795409270.294569064", "1795409270.295857491")
    layouts = {
        id(cache.get(schema_message(stamp, chunk_id=cid), cid.encode(), 0))
        for cid, stamp in zip(ids, stamps, strict=True)
    }
    assert len(layouts) == 1


@pytest.mark.interpreted("services.rrd.layout")
def test_a_schema_read_once_is_then_found_by_cutting_where_its_values_were(monkeypatch: pytest.MonkeyPatch):
    """Reading the flatbuffers for the volatile values costs several times cutting them out where a
    message of the same length had them: after the first chunk of a schema, its chunks are cut."""
    cache = LayoutCache()
    reads: list[bytes] = []
    real = layout.volatile_spans

    def counted(message: bytes) -> layout.Spans:
        reads.append(message)
        return real(message)

    monkeypatch.setattr(layout, "volatile_spans", counted)
    first = cache.get(schema_message("1795409270.262298820", chunk_id=f"chunk_{0:032X}"), f"chunk_{0:032X}".encode(), 0)
    for i in range(1, 50):
        cid = f"chunk_{i:032X}"
        assert cache.get(schema_message(f"17954093{i:02d}.{i:09d}", chunk_id=cid), cid.encode(), 0) is first
    assert len(reads) == 1


def test_schemas_of_one_length_whose_values_sit_elsewhere_keep_their_own_layouts():
    """A cut where another message had its values finds a layout only if the message equals that
    one outside them: a schema of the same length with its values elsewhere is read in full."""
    cache = LayoutCache()
    # The same length (strings are padded to 4 bytes), the stamps one byte apart in length.
    longer_stamp = schema_message("1795409270.111111", "/robot/x")
    longer_path = schema_message("1795409270.11111", "/robot/xx")
    assert len(longer_stamp) == len(longer_path)
    assert volatile_spans(longer_stamp) != volatile_spans(longer_path)
    for _ in range(2):  # each learned, then each found again with the other's spans also known
        assert cache.get(longer_stamp, b"", 0).entity_path == "/robot/x"
        assert cache.get(longer_path, b"", 0).entity_path == "/robot/xx"
        assert cache.get(schema_message("1795409271.000001", "/robot/x"), b"", 0).entity_path == "/robot/x"
        assert cache.get(schema_message("1795409271.00001", "/robot/xx"), b"", 0).entity_path == "/robot/xx"
