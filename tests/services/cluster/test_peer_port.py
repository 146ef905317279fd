"""The peer port takes what one node relays to another, and believes the call's node-to-node
metadata (`fleet-relayed-by`, `fleet-source`) only with that node's peer token (`fleet-peer`): a
client reaching the peer port without it, or with a token of the depot that is not a node's, or
with another node's, is refused. One real `fleet serve` on Postgres (so it has a peer port), auth on."""

from __future__ import annotations

from pathlib import Path

import grpc
import httpx
import pytest
from sqlalchemy.orm import sessionmaker

from services.auth.keys import SigningKey, SigningKeys
from services.auth.tokens import Auth
from tests.conftest import fresh_catalog
from tests.services.cluster.two_nodes import KEY, node, recording, requests_of, token
from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import WRITE_MESSAGES

pytestmark = [pytest.mark.slow, pytest.mark.sdk, pytest.mark.postgres]


def write(addr: str, requests: list[bytes], metadata: list[tuple[str, str]]) -> tuple[grpc.StatusCode, str]:
    with grpc.insecure_channel(addr) as channel:
        call = channel.stream_unary(WRITE_MESSAGES, request_serializer=None, response_deserializer=None)
        try:
            call(iter(requests), timeout=30, metadata=metadata)
        except grpc.RpcError as exc:
            return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
    return grpc.StatusCode.OK, ""


def test_the_peer_port_believes_relay_metadata_only_with_the_relaying_nodes_token(
    request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    nodes_key = Auth(enabled=True, keys=SigningKeys(SigningKey(KEY.encode())), catalog=sessionmaker())
    with fresh_catalog("postgres", request, tmp_path) as url:
        a = node(tmp_path, "a", url).start()
        try:
            listed = httpx.get(f"{a.url}/v1/nodes", headers=a.headers, timeout=10).json()["nodes"]
            (peer_addr,) = [n["peer_addr"] for n in listed if n["id"] == "a"]
            robot = token(a, ["ingest"], "r1")
            requests = requests_of(recording(tmp_path, "run-p", 5))
            caller = [("authorization", f"Bearer {robot}")]
            relayed = [*caller, ("fleet-relayed-by", "x"), ("fleet-source", "upload")]
            refused = [
                relayed,  # no credential
                [*relayed, ("fleet-peer", robot)],  # a robot's token is not a node's
                [*relayed, ("fleet-peer", str(nodes_key.peer_token("y", None, ())))],  # node y's, not x's
                [*relayed, ("fleet-peer", "eyJ.forged.token")],
            ]
            for metadata in refused:
                code, details = write(peer_addr, requests, metadata)
                assert code == grpc.StatusCode.UNAUTHENTICATED, (metadata[1:], details)
                assert "fleet-relayed-by" in details
            # what a node sends: its peer token (no scope of its own) with the caller's token
            code, details = write(
                peer_addr, requests, [*relayed, ("fleet-peer", str(nodes_key.peer_token("x", None, ())))]
            )
            assert code == grpc.StatusCode.OK, details
            assert AuthedDepot(a).failures("grpc", "invalid") >= len(refused)
        finally:
            a.kill()
