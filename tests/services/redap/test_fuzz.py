"""Damaged Arrow and LZ4 in what clients send the catalog service and the peer port, against a real
`fleet serve` with auth on (on Postgres, which gives it its peer port).

FetchChunks' chunk list (a dataframe part holding the keys a manifest handed out) and a chunk
relayed over the peer port (`WriteMessages`, as a node passes a robot's stream on) are damaged in
their Arrow IPC (offsets, node lengths, header bytes: tests/services/rrd/ipc_damage.py) and in
their LZ4 framing (the declared size, the block's bytes). Every answer must be a refusal or a
success (never UNKNOWN, INTERNAL or a dropped connection), the node must stay up, and a chunk the
peer port files must be one that full Arrow validation accepts.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TypeAlias

import grpc
import httpx
import lz4.block
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from services.redap.pb import cloud_pb2
from services.rrd.manifest import read_manifest
from services.rrd.pb import common_pb2, log_msg_pb2, sdk_comms_pb2
from tests.postgres import temporary_database
from tests.services.ingest.live_server import LiveServer
from tests.services.redap.client import Redap
from tests.services.redap.depots import dataset_ids
from tests.services.rrd import hostile
from tests.services.rrd.ipc_damage import damaged, fully_valid
from tests.services.rrd.synthetic import APPLICATION, recording_bytes
from tests.subprocess_server import free_port

pytestmark = [pytest.mark.slow, pytest.mark.postgres]

FUZZ = settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)
Code: TypeAlias = grpc.StatusCode
ANSWERS = {Code.OK, Code.INVALID_ARGUMENT, Code.RESOURCE_EXHAUSTED, Code.NOT_FOUND}
RUN = "fuzz-keys"
ROBOT = "robot-fuzz"
_runs = itertools.count()


@dataclass
class Target:
    live: LiveServer
    peer_port: int
    read: Redap
    ingest_token: str
    keys: list[bytes]


def _token(live: LiveServer, scopes: list[str], robot: str | None = None) -> str:
    body = {"scopes": scopes, "name": "fuzz", **({"robot": robot} if robot else {})}
    answer = httpx.post(f"{live.url}/v1/tokens", json=body, headers=live.headers, timeout=30)
    assert answer.status_code == 201, answer.text
    return str(answer.json()["token"])


@pytest.fixture(scope="module")
def target(tmp_path_factory: pytest.TempPathFactory, migrated_postgres_template: str) -> Iterator[Target]:
    with temporary_database("fleet_fuzz", template=migrated_postgres_template) as url:
        peer_port = free_port()
        live = LiveServer(
            tmp_path_factory.mktemp("fuzz") / "data",
            auth="on",
            catalog_url=url,
            peer_addr=f"127.0.0.1:{peer_port}",
            durability="off",
            catalog_flush_s="0.2",
        ).start()
        try:
            upload = httpx.post(
                f"{live.url}/v1/uploads", content=recording_bytes(RUN), headers=live.headers, timeout=60
            )
            assert upload.status_code == 200, upload.text
            read = Redap(live.grpc_port, _token(live, ["read"]))
            live.wait_for(lambda: APPLICATION in dataset_ids(read), what="the run's dataset")
            request = cloud_pb2.GetRrdManifestRequest(segment_id=common_pb2.SegmentId(id=RUN))
            answers = read.call("GetRrdManifest", request, entry=dataset_ids(read)[APPLICATION])
            keys = pa.concat_tables([read_manifest(a.rrd_manifest) for a in answers]).column("chunk_key").to_pylist()
            assert keys
            yield Target(live, peer_port, read, _token(live, ["ingest"], ROBOT), keys)
            read.close()
        finally:
            live.stop()


def fetch(target: Target, request: bytes) -> tuple[Code, str]:
    call = target.read.channel.unary_stream(
        "/rerun.cloud.v1alpha1.RerunCloudService/FetchChunks", request_serializer=None, response_deserializer=None
    )
    try:
        for _ in call(request, metadata=target.read.metadata(), timeout=60):
            pass
    except grpc.RpcError as exc:
        return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
    return Code.OK, ""


@st.composite
def lz4_framed(draw: st.DrawFn, ipc: bytes) -> tuple[bytes, bool, int]:
    """`ipc` as a message would carry it: uncompressed, or an LZ4 block whose declared size or bytes
    may be off."""
    if not draw(st.booleans(), label="lz4"):
        return ipc, False, len(ipc)
    block = bytearray(lz4.block.compress(ipc, store_size=False))
    declared = len(ipc)
    kind = draw(st.sampled_from(["intact", "declared", "flip", "cut"]), label="lz4 damage")
    if kind == "declared":
        declared = draw(st.sampled_from([0, 1, declared - 1, declared + 1, 2 * declared, 1 << 30, (1 << 31) - 1]))
    elif kind == "flip":
        at = draw(st.integers(0, len(block) - 1), label="position")
        block[at] ^= draw(st.integers(1, 255), label="xor")
    elif kind == "cut":
        del block[draw(st.integers(1, len(block) - 1), label="cut at") :]
    return bytes(block), True, declared


@pytest.mark.timeout(600)
@FUZZ
@given(data=st.data())
def test_damaged_fetch_chunks_requests(target: Target, data: st.DataObject) -> None:
    keys = data.draw(st.lists(st.sampled_from(target.keys), min_size=3, max_size=8), label="keys")
    ipc = hostile.ipc_stream(hostile.chunk_key_table(pa.array(keys, pa.binary())))
    payload, compressed, declared = data.draw(lz4_framed(data.draw(damaged(ipc), label="damaged ipc")), label="framed")
    part = common_pb2.DataframePart(
        encoder_version=common_pb2.ENCODER_VERSION_V0,
        payload=payload,
        compression=common_pb2.COMPRESSION_LZ4 if compressed else common_pb2.COMPRESSION_NONE,
        uncompressed_size=declared,
    )
    code, details = fetch(target, cloud_pb2.FetchChunksRequest(chunk_infos=[part]).SerializeToString())
    assert code in ANSWERS, (code, details)
    assert target.live.healthy(), target.live.log.read_text()[-3000:]


def test_intact_fetch_chunks_request_is_answered(target: Target) -> None:
    ipc = hostile.ipc_stream(hostile.chunk_key_table(pa.array(target.keys, pa.binary())))
    part = common_pb2.DataframePart(payload=ipc, compression=common_pb2.COMPRESSION_NONE, uncompressed_size=len(ipc))
    assert fetch(target, cloud_pb2.FetchChunksRequest(chunk_infos=[part]).SerializeToString()) == (Code.OK, "")


def relay(target: Target, run_id: str, payload: bytes, compressed: bool, declared: int) -> tuple[Code, str]:
    """A stream of one chunk to the peer port, as a node relays a robot's stream."""
    store = common_pb2.StoreId(
        kind=common_pb2.STORE_KIND_RECORDING, recording_id=run_id, application_id=common_pb2.ApplicationId(id="fuzz")
    )
    info = log_msg_pb2.SetStoreInfo(
        row_id=common_pb2.Tuid(time_ns=1, inc=1), info=log_msg_pb2.StoreInfo(store_id=store)
    )
    arrow = log_msg_pb2.ArrowMsg(
        store_id=store,
        chunk_id=common_pb2.Tuid(time_ns=7, inc=0),
        compression=common_pb2.COMPRESSION_LZ4 if compressed else common_pb2.COMPRESSION_NONE,
        uncompressed_size=declared,
        encoding=log_msg_pb2.ENCODING_ARROW_IPC,
        payload=payload,
    )
    requests = [
        sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(set_store_info=info)).SerializeToString(),
        sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(arrow_msg=arrow)).SerializeToString(),
    ]
    md = [("authorization", f"Bearer {target.ingest_token}")]
    with grpc.insecure_channel(f"127.0.0.1:{target.peer_port}") as channel:
        call = channel.stream_unary("/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages", None, None)
        try:
            call(iter(requests), metadata=md, timeout=60)
        except grpc.RpcError as exc:
            return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
    return Code.OK, ""


@pytest.mark.timeout(600)
@FUZZ
@given(data=st.data())
def test_damaged_chunks_relayed_over_the_peer_port(target: Target, data: st.DataObject) -> None:
    ipc = hostile.ipc_stream(hostile.points())
    damaged_ipc = data.draw(damaged(ipc), label="damaged ipc")
    payload, compressed, declared = data.draw(lz4_framed(damaged_ipc), label="framed")
    code, details = relay(target, f"fuzz-peer-{next(_runs)}", payload, compressed, declared)
    assert code in ANSWERS - {Code.NOT_FOUND}, (code, details)
    assert target.live.healthy(), target.live.log.read_text()[-3000:]
    if code == Code.OK:
        assert fully_valid(damaged_ipc), "a chunk that full validation refuses was filed"
