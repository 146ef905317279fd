"""Damaged Arrow inside chunk payloads, sent to a real `fleet serve` over both ingest paths.

tests/services/rrd/test_fuzz.py damages the framing and runs the reader in a worker process; here
the Arrow IPC inside a chunk is damaged (offsets, lengths, buffer positions, validity bitmaps,
flatbuffer header fields), re-compressed with LZ4 (`uncompressed_size` fixed, so only the Arrow is
wrong), and the chunk is sent to a server process by `POST /v1/uploads` and by gRPC
`WriteMessages`, with an ingest token (auth on, as robots send). The chunks damaged are the seed's
property chunk (its values are read at ingest), Scalars, TextLog and Transform3D (read by
analytics), the rest, and Points3D positions (which the depot never reads, so only full validation
sees them). The server must answer every request (2xx or 4xx, never 5xx) and stay alive: its health
is checked after each example; and a chunk it accepts must be one that full Arrow validation
accepts (what Rerun reads): a damaged chunk is never filed.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Iterator

import grpc
import httpx
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from services.rrd.chunk import decompress_payload
from services.rrd.frames import MessageKind
from services.rrd.messages import ArrowMessage, StoreInfoMessage
from services.rrd.pb import log_msg_pb2, sdk_comms_pb2
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd import hostile
from tests.services.rrd.ipc_damage import damaged, fully_valid
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
_runs = itertools.count()
SEED_ROBOT = "robot-seven-of-nine"  # what the seed's fleet property names


@pytest.fixture(scope="module")
def seed(tmp_path_factory: pytest.TempPathFactory) -> Seed:
    return Seed.read(record_seed(tmp_path_factory.mktemp("seed") / "seed.rrd"))


@pytest.fixture(scope="module")
def chunks(seed: Seed) -> list[tuple[ArrowMessage, bytes]]:
    """(message, Arrow IPC) of every chunk: properties, Scalars, TextLog, Transform3D, and a chunk of
    Points3D positions (carried in a Scalars message's envelope)."""
    found = [(e, decompress_payload(e)) for e in seed.events if isinstance(e, ArrowMessage)]
    entities = {entity_of(msg) for msg, _ in found}
    assert {"/__properties/fleet", "/robot/speed", "/log", "/tf"} <= entities
    scalars = next(msg for msg, _ in found if entity_of(msg) == "/robot/speed")
    found.sort(key=lambda chunk: entity_of(chunk[0]) != "/__properties/fleet")  # it first
    return [*found[:1], (scalars, hostile.ipc_stream(hostile.points())), *found[1:]]  # then the points


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    # Housekeeping flushes rarely: streams' runs reach the catalog with the next upload (a flush from
    # the housekeeping thread racing an upload's on the same robot is a DuckDB write conflict).
    live = LiveServer(
        tmp_path_factory.mktemp("fuzzed") / "data", auth="on", durability="off", catalog_flush_s="3600"
    ).start()
    yield live
    live.stop()


@pytest.fixture(scope="module")
def token(server: LiveServer) -> str:
    """An ingest token of the seed's robot (its fleet property names it)."""
    body = {"scopes": ["ingest"], "robot": SEED_ROBOT}
    answer = httpx.post(f"{server.url}/v1/tokens", json=body, headers=server.headers, timeout=30)
    assert answer.status_code == 201, answer.text
    return str(answer.json()["token"])


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
    server: LiveServer, token: str, seed: Seed, chunks: list[tuple[ArrowMessage, bytes]], data: st.DataObject
) -> None:
    # A third of the time each the identity property chunk (its values are read as it is ingested) and
    # the points (never read by the depot: only full validation sees their damage).
    msg, ipc = data.draw(st.one_of(st.just(chunks[0]), st.just(chunks[1]), st.sampled_from(chunks)), label="chunk")
    damaged_ipc = data.draw(damaged(ipc), label="damaged ipc")
    arrow_raw = wrap(msg, damaged_ipc)
    run = next(_runs)
    response = httpx.post(
        f"{server.url}/v1/uploads",
        content=_rrd(_messages(seed, arrow_raw, f"fuzz-{run}")),
        headers={"Authorization": f"Bearer {token}"},
        timeout=60,
    )
    assert response.status_code in ACCEPTED_HTTP, response.text
    if response.status_code != 200:
        assert f"at byte {response.json()['offset']}" in response.json()["message"]
    code, details = server.write_messages(_requests(_messages(seed, arrow_raw, f"fuzz-{run}-grpc")), token=token)
    assert code in ACCEPTED_GRPC, (code, details)
    assert server.healthy(), server.log.read_text()[-3000:]
    if response.status_code == 200 or code == grpc.StatusCode.OK:
        assert fully_valid(damaged_ipc), "a chunk that full validation refuses was filed"


def test_store_infos_are_renamed(seed: Seed) -> None:
    """The runs of the examples are distinct (else every damaged chunk would be a duplicate)."""
    raw = next(bytes(e.raw) for e in seed.events if isinstance(e, StoreInfoMessage))
    assert log_msg_pb2.SetStoreInfo.FromString(renamed_store_info(raw, "x")).info.store_id.recording_id == "x"
