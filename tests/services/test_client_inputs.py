"""Every input a client can send a depot node, hostile, against a real `fleet serve` with auth on (on
Postgres, so it has its peer port too).

The gRPC methods are listed from what a node registers (`server.add_services`): each must have its
hostile requests here (the catalog service's from its descriptor: garbage for every method, and the
hostile dataframe parts for every field that carries one), so a new RPC fails this test until it
has them. REST bodies other than JSON and forms are read only by the upload route and the rules
route (whose hostile files are in tests/services/corpus/test_hostile.py). Every answer must
be the refusal it should be, never UNKNOWN, INTERNAL or a 5xx, and the node must stay up and keep
nothing of what it refused."""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeAlias

import grpc
import httpx
import pytest
from google.protobuf.descriptor import Descriptor

from services.api import peer
from services.auth.tokens import Auth
from services.ingest.grpc_handler import MessageProxy
from services.redap.grpc_handler import STREAMING_CALLS, WRITE_CALLS, CatalogServer
from services.redap.pb import cloud_pb2
from services.rrd.pb import common_pb2, log_msg_pb2, sdk_comms_pb2
from services.server import add_services
from tests.postgres import temporary_database
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd import hostile
from tests.subprocess_server import free_port

pytestmark = [pytest.mark.slow, pytest.mark.postgres]

Code: TypeAlias = grpc.StatusCode
REFUSED = {Code.INVALID_ARGUMENT, Code.RESOURCE_EXHAUSTED}
CLOUD = cloud_pb2.DESCRIPTOR.services_by_name["RerunCloudService"]
CLOUD_PATH = "/rerun.cloud.v1alpha1.RerunCloudService/"
PROXY_PATH = "/rerun.sdk_comms.v1alpha1.MessageProxyService/"
LEGACY_PATH = "/rerun.sdk_comms.v0.MessageProxy/"
PEER_PATH = "/fleet.peer.v1.Peer/"
ROBOT = "robot-hostile"
GARBAGE = b"\xff\xff\xff\xff\x0f garbage"


class _Registry:
    """Stands in for a gRPC server to list the methods a node registers."""

    def __init__(self) -> None:
        self.methods: set[str] = set()

    def add_generic_rpc_handlers(self, handlers: Any) -> None:
        pass

    def add_registered_method_handlers(self, service: str, handlers: dict[str, Any]) -> None:
        self.methods |= {f"/{service}/{name}" for name in handlers}


def served_methods() -> set[str]:
    registry = _Registry()
    off = Auth(enabled=False, keys=None, catalog=None)
    add_services(
        registry,  # type: ignore[arg-type]
        MessageProxy(None, off),  # type: ignore[arg-type]
        CatalogServer(None, off),  # type: ignore[arg-type]
        peer.PeerService(None, None, None),  # type: ignore[arg-type]
    )
    return registry.methods


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory, migrated_postgres_template: str) -> Iterator[Node]:
    with temporary_database("fleet_inputs", template=migrated_postgres_template) as url:
        peer_port = free_port()
        live = LiveServer(
            tmp_path_factory.mktemp("inputs") / "data",
            auth="on",
            catalog_url=url,
            peer_addr=f"127.0.0.1:{peer_port}",
            durability="off",
        ).start()
        try:
            yield Node(live, peer_port)
        finally:
            live.stop()


class Node:
    def __init__(self, live: LiveServer, peer_port: int) -> None:
        self.live = live
        self.peer_port = peer_port
        self.admin = live.headers["Authorization"].split()[1]
        self.read = self._token(["read"])
        self.ingest = self._token(["ingest"], robot=ROBOT)

    def _token(self, scopes: list[str], robot: str | None = None) -> str:
        body = {"scopes": scopes, "name": "hostile", **({"robot": robot} if robot else {})}
        answer = httpx.post(f"{self.live.url}/v1/tokens", json=body, headers=self.live.headers, timeout=30)
        assert answer.status_code == 201, answer.text
        return str(answer.json()["token"])

    def call(
        self,
        path: str,
        request: bytes,
        token: str | None,
        *,
        streaming: bool,
        client_streaming: bool = False,
        port: int | None = None,
        metadata: list[tuple[str, str]] | None = None,
        timeout: float = 30,
    ) -> tuple[Code, str]:
        """One call of raw request bytes: its status and details."""
        md = [*(metadata or []), *([("authorization", f"Bearer {token}")] if token else [])]
        with grpc.insecure_channel(f"127.0.0.1:{port or self.live.grpc_port}") as channel:
            try:
                if client_streaming:
                    channel.stream_unary(path, None, None)(iter([request]), metadata=md, timeout=timeout)
                elif streaming:
                    for _ in channel.unary_stream(path, None, None)(request, metadata=md, timeout=timeout):
                        pass
                else:
                    channel.unary_unary(path, None, None)(request, metadata=md, timeout=timeout)
            except grpc.RpcError as exc:
                return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
        return Code.OK, ""

    def rss(self) -> int:
        """The node's resident memory now, in bytes."""
        for line in Path(f"/proc/{self.live.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise AssertionError("no VmRSS")

    def alive(self) -> None:
        assert self.live.healthy(), self.live.log.read_text()[-3000:]

    def holds_run(self, run_id: str) -> bool:
        answer = httpx.get(f"{self.live.url}/v1/runs/{run_id}", headers=self.live.headers, timeout=30)
        assert answer.status_code in (200, 404), answer.text
        return answer.status_code == 200


# --- the catalog service: every method from its descriptor ----------------------------------------


def dataframe_fields(message: Descriptor, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """Where a request message carries a DataframePart (a client's Arrow table), at any depth."""
    for field in message.fields:
        if field.message_type is None:
            continue
        if field.message_type.full_name == "rerun.common.v1alpha1.DataframePart":
            yield (*path, field.name)
        elif field.message_type.full_name != message.full_name:
            yield from dataframe_fields(field.message_type, (*path, field.name))


def with_part(message: Descriptor, where: tuple[str, ...], part: common_pb2.DataframePart) -> bytes:
    request = message._concrete_class()  # type: ignore[attr-defined]
    target = request
    for name in where[:-1]:
        target = getattr(target, name)
    field = target.DESCRIPTOR.fields_by_name[where[-1]]
    if field.is_repeated:
        getattr(target, where[-1]).add().CopyFrom(part)
    else:
        getattr(target, where[-1]).CopyFrom(part)
    return bytes(request.SerializeToString())


@pytest.mark.parametrize("method", [m.name for m in CLOUD.methods])
def test_catalog_service_refuses_garbage_after_the_token(node: Node, method: str) -> None:
    rpc = CLOUD.methods_by_name[method]
    path, streaming = CLOUD_PATH + method, rpc.server_streaming
    if method == "Version":  # open to anyone, as Rerun's servers answer it
        assert node.call(path, GARBAGE, None, streaming=streaming)[0] == Code.INVALID_ARGUMENT
    else:
        code, details = node.call(path, GARBAGE, None, streaming=streaming)
        assert code == Code.UNAUTHENTICATED, (code, details)  # the token first: nothing parsed without one
        code, details = node.call(path, GARBAGE, node.read, streaming=streaming)
        assert code == Code.INVALID_ARGUMENT and "protobuf" in details, (code, details)
    node.alive()


@pytest.mark.parametrize("method", [m.name for m in CLOUD.methods if any(dataframe_fields(m.input_type))])
def test_catalog_service_refuses_hostile_dataframe_parts(node: Node, method: str) -> None:
    rpc = CLOUD.methods_by_name[method]
    rss_before = node.rss()
    for where in dataframe_fields(rpc.input_type):
        for part in hostile.hostile_dataframe_parts():
            request = with_part(rpc.input_type, where, part)
            code, details = node.call(CLOUD_PATH + method, request, node.read, streaming=rpc.server_streaming)
            assert code in REFUSED, (method, where, code, details)
            node.alive()
    # Parts declaring 1 GiB were refused before anything was allocated.
    assert node.rss() - rss_before < 300 << 20


def test_a_client_version_of_5000_digits_is_invalid(node: Node) -> None:
    request = cloud_pb2.FindEntriesRequest().SerializeToString()
    version = [("x-rerun-client-version", "rerun_py/" + "9" * 5000 + ".1.0")]
    code, _ = node.call(CLOUD_PATH + "FindEntries", request, node.read, streaming=False, metadata=version)
    assert code == Code.INVALID_ARGUMENT


def with_strings(message: Descriptor, value: str, entry: common_pb2.Tuid, depth: int = 0) -> Any:
    """A request of `message`'s type whose every string field, at any depth, holds `value`, and
    every entry id names `entry` (so the request reaches the dataset's segments)."""
    request = message._concrete_class()  # type: ignore[attr-defined]
    if message.full_name == "rerun.common.v1alpha1.Tuid":
        request.CopyFrom(entry)
        return request
    for field in message.fields:
        if field.type == field.TYPE_STRING:
            if field.is_repeated:
                getattr(request, field.name).extend([value, value])
            else:
                setattr(request, field.name, value)
        elif field.message_type is not None and depth < 4 and not field.message_type.GetOptions().map_entry:
            inner = with_strings(field.message_type, value, entry, depth + 1)
            if field.is_repeated:
                getattr(request, field.name).add().CopyFrom(inner)
            elif inner.ByteSize():
                getattr(request, field.name).CopyFrom(inner)
    return request


@pytest.fixture(scope="module")
def dataset_entry(node: Node) -> common_pb2.Tuid:
    """The entry id of a dataset holding one run, uploaded for it."""
    good = hostile.lz4_payload("good", hostile.ipc_stream(hostile.points()))
    answer = httpx.post(
        f"{node.live.url}/v1/uploads",
        content=rrd("strings-run", good),
        headers={"Authorization": f"Bearer {node.ingest}"},
        timeout=60,
    )
    assert answer.status_code == 200, answer.text
    with grpc.insecure_channel(f"127.0.0.1:{node.live.grpc_port}") as channel:
        found = channel.unary_unary(
            CLOUD_PATH + "FindEntries",
            request_serializer=cloud_pb2.FindEntriesRequest.SerializeToString,
            response_deserializer=cloud_pb2.FindEntriesResponse.FromString,
        )(cloud_pb2.FindEntriesRequest(), metadata=[("authorization", f"Bearer {node.read}")], timeout=30)
    ids = [entry.id.id for entry in found.entries if entry.name == "hostile"]
    assert ids, found
    tuid: common_pb2.Tuid = ids[0]
    return tuid


@pytest.mark.parametrize("method", [m.name for m in CLOUD.methods])
def test_catalog_service_refuses_strings_the_catalog_cannot_hold(
    node: Node, dataset_entry: common_pb2.Tuid, method: str
) -> None:
    """Ids and names with a NUL (which Postgres cannot even compare) or 5,000 characters name
    nothing the depot holds: a clear refusal or nothing found, never INTERNAL."""
    rpc = CLOUD.methods_by_name[method]
    entry_header = [("x-rerun-entry-id", f"{dataset_entry.time_ns:016X}{dataset_entry.inc:016x}")]
    for value in ("run\x00id", "x" * 5000, "../../etc"):
        request = with_strings(rpc.input_type, value, dataset_entry).SerializeToString()
        code, details = node.call(
            CLOUD_PATH + method, request, node.read, streaming=rpc.server_streaming, metadata=entry_header
        )
        assert code not in (Code.UNKNOWN, Code.INTERNAL, Code.UNAVAILABLE), (method, value[:20], code, details)
    node.alive()


# --- the message proxy, its 0.22 refusal, and the peer service ----------------------------------------


def set_store_info(run_id: str) -> log_msg_pb2.SetStoreInfo:
    return log_msg_pb2.SetStoreInfo(
        row_id=common_pb2.Tuid(time_ns=1, inc=1),
        info=log_msg_pb2.StoreInfo(
            store_id=common_pb2.StoreId(
                kind=common_pb2.STORE_KIND_RECORDING,
                recording_id=run_id,
                application_id=common_pb2.ApplicationId(id="hostile"),
            ),
        ),
    )


def store_info(run_id: str) -> bytes:
    info = set_store_info(run_id)
    return sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(set_store_info=info)).SerializeToString()


def hostile_stream(run_id: str, payload: hostile.Payload) -> list[bytes]:
    arrow = log_msg_pb2.ArrowMsg.FromString(hostile.arrow_msg(run_id, payload))
    chunk = sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(arrow_msg=arrow)).SerializeToString()
    return [store_info(run_id), chunk]


def write(node: Node, requests: list[bytes], token: str | None, port: int | None = None) -> tuple[Code, str]:
    md = [("authorization", f"Bearer {token}")] if token else []
    with grpc.insecure_channel(f"127.0.0.1:{port or node.live.grpc_port}") as channel:
        try:
            channel.stream_unary(PROXY_PATH + "WriteMessages", None, None)(iter(requests), metadata=md, timeout=60)
        except grpc.RpcError as exc:
            return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
    return Code.OK, ""


def check_write_messages(node: Node) -> None:
    assert write(node, [GARBAGE], node.ingest)[0] == Code.INVALID_ARGUMENT
    for port, where in ((None, "public"), (node.peer_port, "peer")):
        for i, payload in enumerate(hostile.hostile_chunks()):
            run_id = f"hostile-{where}-{i}"
            code, details = write(node, hostile_stream(run_id, payload), node.ingest, port)
            assert code in REFUSED, (where, payload.name, code, details)
            assert not node.holds_run(run_id), (where, payload.name)
            node.alive()


def check_read_messages(node: Node) -> None:
    path = PROXY_PATH + "ReadMessages"
    assert node.call(path, GARBAGE, None, streaming=True)[0] == Code.UNAUTHENTICATED
    # The request has no fields: a read token's call is the live replay, whatever its bytes.
    assert node.call(path, GARBAGE, node.read, streaming=True, timeout=2)[0] == Code.DEADLINE_EXCEEDED


def check_legacy(node: Node) -> None:
    assert node.call(LEGACY_PATH + "WriteMessages", GARBAGE, None, streaming=False, client_streaming=True)[0] == (
        Code.FAILED_PRECONDITION
    )
    assert node.call(LEGACY_PATH + "ReadMessages", GARBAGE, None, streaming=True)[0] == Code.FAILED_PRECONDITION


PEER_BAD_BODIES = [
    b"garbage",
    b"[]",
    json.dumps({"run_id": 5}).encode(),
    json.dumps({"run_id": "r", "include": "/x/**"}).encode(),
    json.dumps({"run_id": "r", "follow": "yes"}).encode(),
    json.dumps({"run_id": "r", "chunk_ids": 5}).encode(),
    json.dumps({"run_id": "r", "chunk_ids": [1, 2]}).encode(),
]


def check_peer(method: str, streaming: bool) -> Callable[[Node], None]:
    def check(node: Node) -> None:
        for port in (None, node.peer_port):
            assert node.call(PEER_PATH + method, b"{}", None, streaming=streaming, port=port)[0] == Code.UNAUTHENTICATED
            for body in PEER_BAD_BODIES:
                code, details = node.call(PEER_PATH + method, body, node.admin, streaming=streaming, port=port)
                assert code in (Code.INVALID_ARGUMENT, Code.NOT_FOUND), (method, body, code, details)
        node.alive()

    return check


NEVER = {Code.UNKNOWN, Code.INTERNAL, Code.OK}
ENTRY_WRITE_ANSWERS = {Code.INVALID_ARGUMENT, Code.UNIMPLEMENTED, Code.NOT_FOUND, Code.FAILED_PRECONDITION}


def check_entry_write(method: str) -> Callable[[Node], None]:
    """A write to an entry that Rerun's protocol has and this depot refuses (a snapshot version never
    changes; other entries' writes are not served): the token first, then whatever the body or the
    entry header holds is one refusal, never a failure."""
    streaming = method in STREAMING_CALLS

    def check(node: Node) -> None:
        path = CLOUD_PATH + method
        assert node.call(path, GARBAGE, None, streaming=streaming)[0] == Code.UNAUTHENTICATED
        assert node.call(path, GARBAGE, node.ingest, streaming=streaming)[0] == Code.PERMISSION_DENIED
        headers: list[list[tuple[str, str]]] = [
            [],
            [("x-rerun-entry-id", "zzz")],
            [("x-rerun-entry-id", "0" * 32)],
            [("x-rerun-entry-id", "f" * 4000)],
        ]
        for metadata in headers:
            for body in (b"", GARBAGE, b"\x0a\x03\x0a\x01\xff"):
                code, details = node.call(path, body, node.read, streaming=streaming, metadata=metadata)
                assert code in ENTRY_WRITE_ANSWERS and code not in NEVER, (method, metadata, body, code, details)
        node.alive()

    return check


HANDWRITTEN: dict[str, Callable[[Node], None]] = {
    PROXY_PATH + "WriteMessages": check_write_messages,
    PROXY_PATH + "ReadMessages": check_read_messages,
    LEGACY_PATH + "WriteMessages": check_legacy,
    LEGACY_PATH + "ReadMessages": check_legacy,
    PEER_PATH + "ReadHot": check_peer("ReadHot", streaming=True),
    PEER_PATH + "Held": check_peer("Held", streaming=False),
    **{CLOUD_PATH + name: check_entry_write(name) for name in WRITE_CALLS if name not in CLOUD.methods_by_name},
}


def test_every_served_method_has_its_hostile_requests() -> None:
    served = served_methods()
    listed = set(HANDWRITTEN) | {CLOUD_PATH + m.name for m in CLOUD.methods}
    assert served - listed == set(), "give these methods their hostile requests in this file"
    assert listed - served == set(), "these methods are no longer served: drop them from this file"


@pytest.mark.parametrize("path", sorted(HANDWRITTEN))
def test_handwritten_methods_refuse_hostile_requests(node: Node, path: str) -> None:
    HANDWRITTEN[path](node)


# --- REST: the upload route, the only one reading a body that is not JSON or a form -------------------


def rrd(run_id: str, payload: hostile.Payload) -> bytes:
    out = bytearray(b"RRF2\x00\x29\x00\x00\x01\x02\x00\x00")  # 0.41.0, LZ4, protobuf
    for kind, raw in ((1, set_store_info(run_id).SerializeToString()), (2, hostile.arrow_msg(run_id, payload))):
        out += struct.pack("<QQ", kind, len(raw)) + raw
    return bytes(out)


def test_uploads_refuse_hostile_chunks(node: Node) -> None:
    for i, payload in enumerate(hostile.hostile_chunks()):
        run_id = f"hostile-upload-{i}"
        answer = httpx.post(
            f"{node.live.url}/v1/uploads",
            content=rrd(run_id, payload),
            headers={"Authorization": f"Bearer {node.ingest}"},
            timeout=60,
        )
        assert answer.status_code in (400, 413), (payload.name, answer.status_code, answer.text)
        assert not node.holds_run(run_id), payload.name
        node.alive()


def test_only_the_upload_route_reads_a_raw_body() -> None:
    services = Path(__file__).resolve().parents[2] / "services"
    readers = sorted(
        p.relative_to(services).as_posix()
        for p in services.rglob("*.py")
        if "request.stream()" in p.read_text() or "request.body()" in p.read_text()
    )
    # each reader's hostile bodies: the uploads' here, the rules file's in tests/services/corpus/test_hostile.py
    assert readers == ["corpus/rest.py", "imports/rest.py"], f"a new route reads a raw body: test it ({readers})"
