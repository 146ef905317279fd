"""Damaged Arrow inside chunk payloads, sent to a real `fleet serve` over both ingest paths.

tests/services/rrd/test_fuzz.py damages the framing and runs the reader in a worker process; here
the Arrow IPC inside a chunk is damaged (offsets, lengths, buffer positions, validity bitmaps,
flatbuffer header fields), re-compressed with LZ4 (`uncompressed_size` fixed, so only the Arrow is
wrong), and the chunk is sent to a server process by `POST /v1/uploads` and by gRPC
`WriteMessages`. The chunks damaged are the seed's property chunk (its values are read at ingest),
Scalars, TextLog and Transform3D (read by analytics) and the rest. The server must answer every
request (2xx or 4xx, never 5xx) and stay alive: its health is checked after each example.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Iterator
from dataclasses import dataclass

import grpc
import httpx
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from services.rrd.chunk import decompress_payload
from services.rrd.frames import MessageKind
from services.rrd.layout import LayoutCache, _parse_batch_header, split_ipc
from services.rrd.messages import ArrowMessage, StoreInfoMessage
from services.rrd.pb import log_msg_pb2, sdk_comms_pb2
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd.malformed import Seed, entity_of, record_seed, renamed_arrow, renamed_store_info, wrap

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

FUZZ = settings(
    max_examples=100,  # ~40 s on 2 cores: two requests and a health check each
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],  # a shrink step per server round trip is not worth it
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)
ACCEPTED_HTTP = {200, 400, 413, 422}
ACCEPTED_GRPC = {grpc.StatusCode.OK, grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.RESOURCE_EXHAUSTED}
INTERESTING_I32 = [0, 1, -1, 7, 255, 1 << 16, 1 << 30, -(1 << 31), (1 << 31) - 1]
INTERESTING_I64 = [0, -1, 1, 1 << 31, 1 << 40, -(1 << 63), (1 << 63) - 1]
_runs = itertools.count()


@pytest.fixture(scope="module")
def seed(tmp_path_factory: pytest.TempPathFactory) -> Seed:
    return Seed.read(record_seed(tmp_path_factory.mktemp("seed") / "seed.rrd"))


@pytest.fixture(scope="module")
def chunks(seed: Seed) -> list[tuple[ArrowMessage, bytes]]:
    """(message, Arrow IPC) of every chunk: properties, Scalars, TextLog, Transform3D."""
    found = [(e, decompress_payload(e)) for e in seed.events if isinstance(e, ArrowMessage)]
    entities = {entity_of(msg) for msg, _ in found}
    assert {"/__properties/fleet", "/robot/speed", "/log", "/tf"} <= entities
    return sorted(found, key=lambda chunk: entity_of(chunk[0]) != "/__properties/fleet")  # it first


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    # Housekeeping flushes rarely: streams' runs reach the catalog with the next upload (a flush from
    # the housekeeping thread racing an upload's on the same robot is a DuckDB write conflict).
    live = LiveServer(tmp_path_factory.mktemp("fuzzed") / "data", durability="off", catalog_flush_s="3600").start()
    yield live
    live.stop()


@dataclass
class IpcMap:
    """Where things are in a chunk's Arrow IPC stream: the record batch header (flatbuffer), its
    field nodes (length, null count) and each buffer (validity bitmaps, offsets, values)."""

    header: tuple[int, int]
    nodes: int  # position of the first node's length
    num_nodes: int
    buffers: list[tuple[int, int]]  # (start, length) of the non-empty buffers

    @classmethod
    def of(cls, ipc: bytes) -> IpcMap:
        found = split_ipc(ipc)
        assert found is not None
        schema_message, pos = found
        parsed = _parse_batch_header(ipc, pos, LayoutCache().get(schema_message, b"", 0))
        assert parsed is not None
        header, template = parsed
        assert header is not None and template is not None
        flat = header.buffers
        buffers = [(header.body + flat[i], flat[i + 1]) for i in range(0, len(flat), 2) if flat[i + 1] >= 4]
        return cls((pos + 8, header.body), pos + 8 + template.at_nodes, len(header.nodes) // 2, buffers)

    def offsets_buffers(self, ipc: bytes) -> list[tuple[int, int]]:
        """(start, entries) of the buffers that look like list or string offsets: int32s from 0,
        never decreasing, at least 3 (so there is a middle one, which a cheap check never reads)."""
        found = []
        for start, length in self.buffers:
            values = struct.unpack_from(f"<{length // 4}i", ipc, start)
            n = len(values)
            while n > 3 and values[n - 1] == 0:  # padding
                n -= 1
            if n >= 3 and values[0] == 0 and all(a <= b for a, b in itertools.pairwise(values[:n])):
                found.append((start, n))
        return found


@st.composite
def damaged(draw: st.DrawFn, ipc: bytes) -> bytes:
    """`ipc` with 1 to 3 edits, aimed where Arrow readers trust the data: an int32 in a buffer (list
    and string offsets) set to a boundary value or moved a little, a bit of a buffer flipped
    (validity bitmaps, values), a field node's length or null count changed, a byte of the record
    batch header flipped (buffer positions, body length), or any byte flipped."""
    data = bytearray(ipc)
    where = IpcMap.of(ipc)
    offsets = where.offsets_buffers(ipc)
    for _ in range(draw(st.integers(1, 3), label="edits")):
        kind = draw(st.sampled_from(["list offset", "offset", "bit", "node", "header", "byte"]), label="kind")
        if kind == "list offset" and offsets:  # a middle offset out of order or past the values
            start, entries = draw(st.sampled_from(offsets), label="offsets buffer")
            pos = start + 4 * draw(st.integers(1, entries - 2), label="entry")
            old = struct.unpack_from("<i", data, pos)[0]
            new = draw(st.sampled_from([old + (1 << 30), old + 1000, -1, -(1 << 31), old + 2]), label="offset")
            data[pos : pos + 4] = struct.pack("<i", max(-(1 << 31), min(new, (1 << 31) - 1)))
        elif kind in ("offset", "bit") and where.buffers:
            if kind == "offset":  # any int32 of any buffer: long offsets buffers are hit most
                slots = [start + 4 * i for start, length in where.buffers for i in range(length // 4)]
                pos = draw(st.sampled_from(slots), label="slot")
                old = struct.unpack_from("<i", data, pos)[0]
                new = draw(
                    st.one_of(
                        st.sampled_from(INTERESTING_I32), st.integers(old - 3, old + 3), st.just(old + (1 << 30))
                    ),
                    label="int32",
                )
                data[pos : pos + 4] = struct.pack("<i", max(-(1 << 31), min(new, (1 << 31) - 1)))
            else:
                start, length = draw(st.sampled_from(where.buffers), label="buffer")
                pos = draw(st.integers(start, start + length - 1), label="position")
                data[pos] ^= 1 << draw(st.integers(0, 7), label="bit")
        elif kind == "node" and where.num_nodes:
            pos = where.nodes + 8 * draw(st.integers(0, 2 * where.num_nodes - 1), label="node field")
            data[pos : pos + 8] = struct.pack("<q", draw(st.sampled_from([*INTERESTING_I64, 2, 3, 5]), label="int64"))
        elif kind == "header":
            pos = draw(st.integers(where.header[0], where.header[1] - 1), label="position")
            data[pos] ^= draw(st.integers(1, 255), label="xor")
        else:
            pos = draw(st.integers(0, len(data) - 1), label="position")
            data[pos] ^= draw(st.integers(1, 255), label="xor")
    return bytes(data)


def _messages(seed: Seed, arrow_raw: bytes, run_id: str) -> list[tuple[MessageKind, bytes]]:
    """The recording's store infos, then the damaged chunk, as run `run_id`."""
    infos = [(kind, raw) for kind, raw in seed.messages(recording_id=run_id) if kind == MessageKind.SET_STORE_INFO]
    return [*infos, (MessageKind.ARROW_MSG, renamed_arrow(arrow_raw, run_id))]


def _rrd(messages: list[tuple[MessageKind, bytes]]) -> bytes:
    out = bytearray(b"RRF2\x00\x29\x00\x00\x01\x00\x00\x00")  # 0.41.0, LZ4, Protobuf
    for kind, raw in messages:
        out += struct.pack("<QQ", int(kind), len(raw)) + raw
    return bytes(out)


def _requests(messages: list[tuple[MessageKind, bytes]]) -> list[bytes]:
    out = []
    for kind, raw in messages:
        inner = (
            log_msg_pb2.LogMsg(set_store_info=log_msg_pb2.SetStoreInfo.FromString(raw))
            if kind == MessageKind.SET_STORE_INFO
            else log_msg_pb2.LogMsg(arrow_msg=log_msg_pb2.ArrowMsg.FromString(raw))
        )
        out.append(sdk_comms_pb2.WriteMessagesRequest(log_msg=inner).SerializeToString())
    return out


@pytest.mark.timeout(300)
@FUZZ
@given(data=st.data())
def test_damaged_arrow_in_chunks_never_takes_the_server_down(
    server: LiveServer, seed: Seed, chunks: list[tuple[ArrowMessage, bytes]], data: st.DataObject
) -> None:
    # Half the time the identity property chunk: its values are read as it is ingested.
    msg, ipc = data.draw(st.one_of(st.just(chunks[0]), st.sampled_from(chunks)), label="chunk")
    arrow_raw = wrap(msg, data.draw(damaged(ipc), label="damaged ipc"))
    run = next(_runs)
    response = httpx.post(
        f"{server.url}/v1/uploads", content=_rrd(_messages(seed, arrow_raw, f"fuzz-{run}")), timeout=60
    )
    assert response.status_code in ACCEPTED_HTTP, response.text
    if response.status_code != 200:
        assert f"at byte {response.json()['offset']}" in response.json()["message"]
    code, details = server.write_messages(_requests(_messages(seed, arrow_raw, f"fuzz-{run}-grpc")))
    assert code in ACCEPTED_GRPC, (code, details)
    assert server.healthy(), server.log.read_text()[-3000:]


def test_store_infos_are_renamed(seed: Seed) -> None:
    """The runs of the examples are distinct (else every damaged chunk would be a duplicate)."""
    raw = next(bytes(e.raw) for e in seed.events if isinstance(e, StoreInfoMessage))
    assert log_msg_pb2.SetStoreInfo.FromString(renamed_store_info(raw, "x")).info.store_id.recording_id == "x"
