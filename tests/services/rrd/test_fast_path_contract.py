"""Contract tests of the codec's hand-written fast paths.

Where BENCHMARKS.md ("Codec: scan + index") shows pyarrow or the protobuf classes too slow, the
codec reads bytes by hand, on assumptions about the layout Arrow and Rerun write. Each test here
reads every message of real recordings written by the pinned rerun-sdk (and re-encoded by its CLI)
both ways, the fast path and the reference library, and on a difference fails with a message that
starts "assumption broken:" and names the assumption, so that a new pyarrow or rerun-sdk that
changes the layout says which fast path to revisit.

Pinned elsewhere: rows, timeline and component ranges from the batch header against pyarrow
(test_layout.py), large payloads kept as views (test_layout.py), the Scalars offsets check against
full validation on damaged chunks (test_validate.py, test_value_checks.py), chunk ids against the Arrow metadata
(test_chunk.py), the footer summary against a scan (test_summary.py).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from services.ingest.requests import unwrap
from services.rrd import ArrowMessage, chunk, decoder, errors, iter_events, lz4_prefix, protowire
from services.rrd.batch_plan import batch_plan
from services.rrd.chunk import chunk_meta, decompress_payload, read_chunk
from services.rrd.footer import read_footer
from services.rrd.frames import MessageKind
from services.rrd.layout import BatchHeader, ChunkLayout, _parse_batch_header, read_batch_header, split_ipc
from services.rrd.messages import EndMessage, Message, StreamFooter, chunk_id_str
from services.rrd.pb import log_msg_pb2, sdk_comms_pb2
from services.rrd.value_checks import values_valid
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

IPC_FRAMING = (
    "an Arrow IPC stream starts with the schema message (0xFFFFFFFF, int32 metadata size, the "
    "flatbuffer, no body) and the record batch message follows at once (layout.split_ipc)"
)
BATCH_HEADER = (
    "a record batch's flatbuffer header (Message: header type, header, bodyLength; RecordBatch: "
    "length, nodes, buffers, no compression) is read by hand (layout._parse_batch_header, "
    "BatchTemplate.match)"
)
NODES_AND_BUFFERS = (
    "an Arrow type takes the field nodes and buffers layout._counts gives it in an IPC record "
    "batch, children after their parent, in column order"
)
SORTED_INDEX = (
    "an index column marked rerun:is_sorted=true is sorted ascending, so its first and last values "
    "are its range (chunk._read_ranges)"
)
OFFSETS_BUFFERS = (
    "an array's buffers are its validity bitmap then, for a list or map its offsets (its child follows), "
    "for a binary or string its offsets then its bytes, in the order of its field nodes "
    "(value_checks.value_checks, values_valid)"
)
METADATA_FIRST = (
    "a chunk's IPC payload holds its schema, record batch header, row ids and index columns before "
    "its data columns, so a large chunk's metadata is read from its first bytes (chunk.chunk_meta)"
)
LZ4_PREFIX = (
    "liblz4's LZ4_decompress_safe_partial is reachable in python-lz4's extension and gives the first "
    "bytes of what lz4.block gives (lz4_prefix)"
)
SCHEMA_KEY = (
    "a chunk's schema message holds its chunk id only as the text chunk_<hex> (rerun:id), so the "
    "schema messages of chunks with one schema are equal once it is blanked (layout.LayoutCache)"
)
ARROW_MSG_AROUND_PAYLOAD = (
    "an ArrowMsg read around its payload (protowire finds field 5, protobuf parses the "
    "rest) is the message protobuf parses whole (decoder._arrow_message, large messages)"
)
GRPC_UNWRAP = (
    "a WriteMessagesRequest holds its LogMsg in field 1, and LogMsg's oneof fields 1-3 are message "
    "kinds 1-3 (ingest.requests.unwrap)"
)
STREAM_FOOTER = (
    "a single-stream file ends with the stream footer (u64 start, u64 length, u32 xxh32, "
    "b'RRF2FOOT', u32 1) pointing at the End message's RrdFooter (footer.read_footer)"
)


def broken(assumption: str, where: str, detail: object = "") -> str:
    return f"assumption broken: {assumption}\n  at {where}: {detail}"


@contextmanager
def assuming(assumption: str, where: str) -> Iterator[None]:
    """A codec error from a fast path also names the assumption."""
    try:
        yield
    except errors.RrdError as exc:
        pytest.fail(broken(assumption, where, f"{type(exc).__name__}: {exc}"))


def _chunks(rec: Recording) -> Iterator[tuple[ArrowMessage, bytes, str]]:
    """Each Arrow message, its IPC stream, and where it is (for failure messages)."""
    for event in iter_events(rec.path):
        if isinstance(event, ArrowMessage):
            yield event, decompress_payload(event), f"{rec.name}.rrd, message at byte {event.offset}"


def _ipc_messages(data: bytes) -> tuple[pa.Buffer, pa.ipc.Message, int, pa.ipc.Message]:
    """pyarrow's reading of an IPC stream: (its buffer, schema message, where the next starts, batch message)."""
    buffer = pa.py_buffer(data)
    reader = pa.BufferReader(buffer)
    schema_message = pa.ipc.read_message(reader)
    after = reader.tell()
    return buffer, schema_message, after, pa.ipc.read_message(reader)


def _arrays(array: pa.Array) -> Iterator[pa.Array]:
    """An array and its descendants depth first: one IPC field node each (children as stored, no
    parent offset applied, as an IPC reader builds them)."""
    yield array
    kind = array.type
    if (
        pa.types.is_list(kind)
        or pa.types.is_large_list(kind)
        or pa.types.is_fixed_size_list(kind)
        or pa.types.is_map(kind)
    ):
        yield from _arrays(array.values)
    elif pa.types.is_struct(kind):
        for i in range(kind.num_fields):
            yield from _arrays(array.field(i))


def _header(data: bytes, layout: ChunkLayout, where: str) -> BatchHeader:
    split = split_ipc(data)
    assert split is not None, broken(IPC_FRAMING, where, "split_ipc found no schema message")
    header = read_batch_header(data, split[1], layout)
    assert header is not None, broken(
        BATCH_HEADER, where, "the header was not read: every chunk falls back to pyarrow (slow, not wrong)"
    )
    return header


def test_ipc_stream_framing_is_what_pyarrow_reads(whole: Recording):
    for _, data, where in _chunks(whole):
        found = split_ipc(data)
        _, schema_message, after, batch_message = _ipc_messages(data)
        assert found is not None, broken(IPC_FRAMING, where, "split_ipc found no schema message")
        assert schema_message.type == "schema" and batch_message.type == "record batch", broken(
            IPC_FRAMING, where, f"pyarrow reads a {schema_message.type} then a {batch_message.type}"
        )
        assert found[0] == schema_message.metadata.to_pybytes(), broken(IPC_FRAMING, where, "schema flatbuffer")
        assert found[1] == after, broken(IPC_FRAMING, where, f"next message at {found[1]}, pyarrow: {after}")


def test_record_batch_header_read_by_hand_is_what_pyarrow_reads(whole: Recording):
    for msg, data, where in _chunks(whole):
        layout = chunk_meta(msg).layout
        assert layout.direct, broken(NODES_AND_BUFFERS, where, f"a type is not counted: {layout.schema}")
        buffer, schema_message, after, batch_message = _ipc_messages(data)
        batch = pa.ipc.read_record_batch(batch_message, pa.ipc.read_schema(schema_message))
        body = batch_message.body
        nodes = tuple(n for column in batch.columns for a in _arrays(column) for n in (len(a), a.null_count))
        buffers = [b for column in batch.columns for b in column.buffers()]
        parsed = _parse_batch_header(data, after, layout)
        assert parsed is not None and parsed[0] is not None, broken(BATCH_HEADER, where, "not parsed")
        headers = [("parsed", parsed[0])]
        for template in layout.batch_templates:  # made from the first chunk of this layout
            matched = template.match(data, after)
            if matched is not None:  # else the header is parsed: slower, not wrong
                headers.append(("templated", matched))
        for how, header in headers:
            detail = f"{how} header"
            assert header.length == batch.num_rows, broken(
                BATCH_HEADER, where, f"{detail}: length {header.length}, pyarrow: {batch.num_rows} rows"
            )
            assert header.body == body.address - buffer.address, broken(BATCH_HEADER, where, f"{detail}: body")
            assert header.nodes == nodes, broken(
                BATCH_HEADER, where, f"{detail}: nodes {header.nodes}, pyarrow: {nodes}"
            )
            assert len(header.buffers) == 2 * len(buffers), broken(BATCH_HEADER, where, f"{detail}: buffer count")
            for i, reference in enumerate(buffers):
                if reference is None:
                    continue  # pyarrow drops a validity bitmap without nulls, which the writer may keep
                got, want = header.buffers[2 * i : 2 * i + 2], (reference.address - body.address, reference.size)
                assert got == want, broken(BATCH_HEADER, where, f"{detail}: buffer {i} is {got}, pyarrow: {want}")


def test_nodes_and_buffers_counted_per_type_are_arrows(whole: Recording):
    for msg, _, where in _chunks(whole):
        layout = chunk_meta(msg).layout
        batch = read_chunk(msg)
        node = buffer = 0
        first_node, first_buffer = [], []
        for position, column in enumerate(batch.columns):
            first_node.append(node)
            first_buffer.append(buffer)
            node, buffer = node + len(list(_arrays(column))), buffer + len(column.buffers())
            assert layout.top_nodes[position] == first_node[-1], broken(
                NODES_AND_BUFFERS,
                where,
                f"column {position} ({column.type}) starts at node "
                f"{layout.top_nodes[position]}, pyarrow: {first_node[-1]}",
            )
        assert (layout.num_nodes, layout.num_buffers) == (node, buffer), broken(
            NODES_AND_BUFFERS,
            where,
            f"{layout.num_nodes} nodes, {layout.num_buffers} buffers; pyarrow: {node}, "
            f"{buffer} for {[str(t) for t in batch.schema.types]}",
        )
        for ix in layout.indexes:  # validity, then values
            assert (ix.node, ix.data_buffer) == (first_node[ix.position], first_buffer[ix.position] + 1), broken(
                NODES_AND_BUFFERS, where, f"index column {ix.name!r}"
            )
        for c in layout.data:
            assert (c.node, c.buffer) == (first_node[c.position], first_buffer[c.position]), broken(
                NODES_AND_BUFFERS, where, f"column {c.column!r} ({c.field.type})"
            )


def test_sorted_index_columns_are_sorted(whole: Recording):
    for msg, _, where in _chunks(whole):
        meta = chunk_meta(msg)
        batch = read_chunk(msg)
        for ix in meta.layout.indexes:
            values = batch.column(ix.position).cast(pa.int64())
            if ix.is_sorted and len(values) > 1:
                ascending = pc.all(pc.greater_equal(values[1:], values[:-1])).as_py()
                assert ascending, broken(SORTED_INDEX, where, f"timeline {ix.name!r}: {values.to_pylist()}")
            if len(values):
                low_high = pc.min_max(values).as_py()
                timeline = next(t for t in meta.timelines if t.name == ix.name)
                assert (timeline.range.min, timeline.range.max) == (low_high["min"], low_high["max"]), broken(
                    SORTED_INDEX, where, f"timeline {ix.name!r}"
                )


def _offsets_arrays(array: pa.Array) -> Iterator[tuple[pa.Array, int, int]]:
    """Each array with offsets under `array`, depth first, with its last offset's limit (its child's
    length, or its bytes' size) and where its bytes start (-1: not a string)."""
    for a in _arrays(array):
        kind = a.type
        if pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_map(kind):
            yield a, len(a.values), -1
        elif pa.types.is_string(kind) or pa.types.is_large_string(kind):
            yield a, a.buffers()[2].size, a.buffers()[2].address
        elif pa.types.is_binary(kind) or pa.types.is_large_binary(kind):
            yield a, a.buffers()[2].size, -1


_NO_OFFSETS: set[str] = set()  # recordings with no array of offsets (none so far)


def test_offsets_checked_by_hand_are_arrows(whole: Recording):
    """The offsets value_checks reads from a record batch's body, and what it checks them against,
    are pyarrow's, for every array with offsets of every chunk of every recording."""
    checked = 0
    for rec in [whole]:
        for msg, data, where in _chunks(rec):
            meta = chunk_meta(msg)
            split = split_ipc(data)
            assert split is not None
            plan = batch_plan(data, split[1], meta.layout, len(data)) if meta.layout.direct else None
            if plan is None or plan.checks is None:
                continue
            buffer, schema_message, _, batch_message = _ipc_messages(data)
            batch = pa.ipc.read_record_batch(batch_message, pa.ipc.read_schema(schema_message))
            batch.validate(full=True)
            arrays = [found for column in batch.columns for found in _offsets_arrays(column) if len(found[0])]
            assert len(arrays) == len(plan.checks), broken(OFFSETS_BUFFERS, where, f"{len(plan.checks)} checks")
            for check, (array, limit, text_at) in zip(plan.checks, arrays, strict=True):
                dtype = "<i8" if check.wide else "<i4"
                offsets = np.frombuffer(data, dtype=dtype, count=check.count, offset=split[1] + check.at)
                width = 8 if check.wide else 4
                want = np.frombuffer(array.buffers()[1], dtype=dtype, count=len(array) + 1, offset=width * array.offset)
                assert offsets.tolist() == want.tolist(), broken(OFFSETS_BUFFERS, where, array.type)
                assert check.limit == limit, broken(OFFSETS_BUFFERS, where, f"{array.type}: limit {check.limit}")
                if text_at >= 0:
                    got = buffer.address + split[1] + check.text_at
                    assert got == text_at, broken(OFFSETS_BUFFERS, where, f"{array.type}: bytes")
            assert values_valid(data, split[1], plan.checks), broken(OFFSETS_BUFFERS, where, "a valid chunk failed")
            checked += len(arrays)
    assert checked or whole.name in _NO_OFFSETS, f"no chunk of {whole.name} had its offsets checked by hand"


def test_schema_messages_differ_only_in_the_chunk_id(whole: Recording):
    # keyed by the whole schema, field metadata too (pa.Schema's == ignores it: chunks that differ
    # only in, say, whether a timeline is sorted have two schemas, rightly two cache keys)
    keys_by_schema: dict[bytes, set[bytes]] = {}
    for msg, data, where in _chunks(whole):
        split = split_ipc(data)
        assert split is not None and msg.chunk_id is not None
        id_text = chunk_id_str(msg.chunk_id).encode()
        assert split[0].count(id_text) == 1, broken(
            SCHEMA_KEY, where, f"{id_text!r} appears {split[0].count(id_text)} times"
        )
        schema = read_chunk(msg).schema
        metadata = {k: v for k, v in (schema.metadata or {}).items() if v != id_text}
        assert len(metadata) == len(schema.metadata or {}) - 1, broken(SCHEMA_KEY, where, "rerun:id")
        whole_schema = schema.with_metadata(metadata).serialize().to_pybytes()
        keys_by_schema.setdefault(whole_schema, set()).add(split[0].replace(id_text, b""))
    for serialized, keys in keys_by_schema.items():
        schema = pa.ipc.read_schema(pa.py_buffer(serialized))
        assert len(keys) == 1, broken(
            SCHEMA_KEY, whole.name, f"{len(keys)} keys for one schema (a cache miss per chunk): {schema}"
        )


def test_arrow_message_read_around_its_payload_is_protobufs(whole: Recording, monkeypatch: pytest.MonkeyPatch):
    descriptor = log_msg_pb2.ArrowMsg.DESCRIPTOR
    assert descriptor.fields_by_name["payload"].number == decoder._ARROW_PAYLOAD_FIELD, broken(
        ARROW_MSG_AROUND_PAYLOAD, "log_msg.proto", "the payload's field number"
    )
    messages = [(msg, where) for msg, _, where in _chunks(whole)]
    monkeypatch.setattr(decoder, "LARGE_MESSAGE", 0)  # every message read the large way
    for msg, where in messages:
        raw = bytes(msg.raw)
        whole_pb = log_msg_pb2.ArrowMsg.FromString(raw)
        walked = Counter(number for number, *_ in protowire.fields(raw))
        assert walked == Counter(f.number for f, _ in whole_pb.ListFields()), broken(
            ARROW_MSG_AROUND_PAYLOAD, where, f"protowire walks fields {walked}"
        )
        with assuming(ARROW_MSG_AROUND_PAYLOAD, where):
            around = decoder.decode_message(MessageKind.ARROW_MSG, raw, msg.offset)
        assert isinstance(around, ArrowMessage) and isinstance(around.payload, memoryview)
        assert bytes(around.payload) == whole_pb.payload, broken(ARROW_MSG_AROUND_PAYLOAD, where, "payload")
        fields = ("store_id", "chunk_id", "is_static", "compression", "uncompressed_size")
        assert [getattr(around, f) for f in fields] == [getattr(msg, f) for f in fields], broken(
            ARROW_MSG_AROUND_PAYLOAD, where, "the fields beside the payload"
        )


# Each message kind: its LogMsg field and its protobuf class.
_LOG_MSG_FIELDS: dict[int, tuple[str, type[Any]]] = {
    MessageKind.SET_STORE_INFO: ("set_store_info", log_msg_pb2.SetStoreInfo),
    MessageKind.ARROW_MSG: ("arrow_msg", log_msg_pb2.ArrowMsg),
    MessageKind.BLUEPRINT_ACTIVATION: ("blueprint_activation_command", log_msg_pb2.BlueprintActivationCommand),
}


def test_grpc_requests_unwrapped_by_hand_are_protobufs(whole: Recording):
    assert sdk_comms_pb2.WriteMessagesRequest.DESCRIPTOR.fields_by_name["log_msg"].number == 1, broken(
        GRPC_UNWRAP, "sdk_comms.proto", "WriteMessagesRequest.log_msg"
    )
    for message_kind, (name, _) in _LOG_MSG_FIELDS.items():
        assert log_msg_pb2.LogMsg.DESCRIPTOR.fields_by_name[name].number == message_kind, broken(
            GRPC_UNWRAP, "log_msg.proto", f"LogMsg.{name}"
        )
    seen: Counter[int] = Counter()
    for event in iter_events(whole.path):
        if not isinstance(event, Message) or isinstance(event, EndMessage):
            continue
        name, message_class = _LOG_MSG_FIELDS[event.kind]
        inner = message_class.FromString(bytes(event.raw))
        request = sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(**{name: inner}))
        where = f"{whole.name}.rrd, message at byte {event.offset}"
        with assuming(GRPC_UNWRAP, where):
            kind, raw = unwrap(request.SerializeToString(), 0)
        assert (kind, bytes(raw)) == (event.kind, inner.SerializeToString()), broken(GRPC_UNWRAP, where, f"kind {kind}")
        seen[event.kind] += 1
    assert seen[MessageKind.SET_STORE_INFO] and seen[MessageKind.ARROW_MSG]


def test_footer_read_from_the_end_is_the_one_scanned(footer_file: Recording):
    events = list(iter_events(footer_file.path))
    ends = [e for e in events if isinstance(e, EndMessage)]
    trailers = [e for e in events if isinstance(e, StreamFooter)]
    assert len(ends) == len(trailers) == 1 and ends[0].footer is not None
    assert trailers[0].footer_start == ends[0].stream_payload_offset, broken(STREAM_FOOTER, footer_file.name)
    with open(footer_file.path, "rb") as fh:
        footer = read_footer(fh)
    assert footer == ends[0].footer, broken(
        STREAM_FOOTER, f"{footer_file.name}.rrd", "read_footer gives None" if footer is None else "another footer"
    )


def _summary(meta: chunk.ChunkMeta) -> tuple[object, ...]:
    return (
        meta.chunk_id,
        meta.entity_path,
        meta.num_rows,
        [(t.name, t.type, t.range, t.is_sorted) for t in meta.timelines],
        [(c.column, c.num_rows, c.ranges) for c in meta.components],
        meta.uncompressed_size,
        meta.problem,
    )


def test_chunk_metadata_precedes_the_data_columns(whole: Recording):
    """Read from only the bytes it says it needs, a chunk's metadata is the one read from the whole
    payload, and those bytes end before its first data column's values (where the data lies)."""
    large = 0
    for msg, data, where in _chunks(whole):
        full, needed = chunk._chunk_meta(msg, data, len(data))
        if needed == len(data):
            continue  # read whole: its values are read, or pyarrow reads it (nulls in a column)
        prefix, again = chunk._chunk_meta(msg, data[:needed], len(data))
        assert _summary(prefix) == _summary(full) and again == needed, broken(METADATA_FIRST, where, "another result")
        assert not prefix.values_checked  # its values are checked at ingest from the whole payload (check_chunk)
        header = _header(data, full.layout, where)
        data_starts = [
            header.body + header.buffers[2 * b]
            for c in full.layout.data
            for b in range(c.buffer, c.buffer + 2)
            if header.buffers[2 * b + 1]
        ]
        if data_starts:
            assert needed <= min(data_starts), broken(
                METADATA_FIRST, where, f"{needed} bytes needed, data from byte {min(data_starts)}"
            )
        large += len(data) >= chunk.PREFIX_FROM_BYTES
    if whole.name == "large":
        assert large, "no chunk of the large recording is large enough for the prefix path"


def test_lz4_prefix_is_lz4s(recordings: dict[str, Recording]):
    assert lz4_prefix.available, broken(LZ4_PREFIX, "lz4.block._block", "LZ4_decompress_safe_partial not found")
    for msg, data, where in _chunks(recordings["large"]):
        for size in sorted({1, min(4096, len(data)), len(data) // 2 or 1, len(data)}):
            assert lz4_prefix.decompress_prefix(msg.payload, size) == data[:size], broken(LZ4_PREFIX, where, size)
        with pytest.raises(ValueError):
            lz4_prefix.decompress_prefix(msg.payload, len(data) + 1)  # the block holds no more


def test_large_chunks_read_through_the_prefix(whole: Recording, monkeypatch: pytest.MonkeyPatch):
    """Every chunk's metadata through the prefix path (on real recordings the guess is sometimes too
    short: then more is decompressed) is the one read from the whole payload."""
    chunks = list(_chunks(whole))
    expected = [_summary(chunk_meta(msg)) for msg, _, _ in chunks]
    monkeypatch.setattr(chunk, "PREFIX_FROM_BYTES", 0)
    monkeypatch.setattr(chunk, "_prefix_guess", 64)
    for (msg, _, where), want in zip(chunks, expected, strict=True):
        with assuming(METADATA_FIRST, where):
            got = _summary(chunk_meta(msg))
        assert got == want, broken(METADATA_FIRST, where, "another result through the prefix")
