"""Malformed chunks and secrets against a real `fleet serve`, over `POST /v1/uploads` and gRPC.

Each chunk that `rerun rrd verify` refuses (tests/services/rrd/malformed.py) is refused by both ingest
paths with a 400 / INVALID_ARGUMENT naming it, and the server stays up for everyone else. Among them
is the ~1.3 KB property chunk whose list offsets point 1 GiB past its values: reading it killed the
server with SIGSEGV (finding 2).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest

from services.rrd import ArrowMessage, RrdDecoder
from services.rrd.messages import chunk_id_str
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd.malformed import MALFORMED, Seed, malformed_chunk, record_seed

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def seed(tmp_path_factory: pytest.TempPathFactory) -> Seed:
    return Seed.read(record_seed(tmp_path_factory.mktemp("seed") / "seed.rrd"))


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    # Streams' runs reach the catalog with the next upload's flush, not from the housekeeping thread:
    # that flush racing an upload's on the same robot row fails with a DuckDB write conflict (a 500),
    # which is not what these tests are about.
    live = LiveServer(tmp_path_factory.mktemp("served") / "data", durability="off", catalog_flush_s="3600").start()
    yield live
    live.stop()


def _offset_of(data: bytes, chunk_id: bytes | None) -> int:
    decoder = RrdDecoder()
    return next(e.offset for e in decoder.feed(data) if isinstance(e, ArrowMessage) and e.chunk_id == chunk_id)


@pytest.mark.parametrize("variant", MALFORMED)
def test_both_ingest_paths_refuse_the_variant(server: LiveServer, seed: Seed, variant: str) -> None:
    msg, raw = malformed_chunk(seed, variant)
    run_id = "bad-" + variant.replace("_", "-")
    data = seed.stream({msg.offset: raw}, run_id)
    response = httpx.post(f"{server.url}/v1/uploads", content=data, timeout=60)
    assert response.status_code == 400, response.text
    body = response.json()
    assert body["code"] == "INVALID_RRD"
    assert body["offset"] == _offset_of(data, msg.chunk_id)
    assert f"at byte {body['offset']}" in body["message"]
    if not variant.startswith(("index_", "scalars_column", "index_column")):  # refused reading the header
        assert msg.chunk_id is not None and chunk_id_str(msg.chunk_id) in body["message"]
        assert f"entity {MALFORMED[variant][0]}" in body["message"]
    code, details = server.write_messages(seed.grpc_requests({msg.offset: raw}, run_id + "-grpc"))
    assert code == grpc.StatusCode.INVALID_ARGUMENT, (code, details)
    assert server.healthy(), server.log.read_text()[-3000:]


def test_the_server_still_ingests_after_them(server: LiveServer, seed: Seed) -> None:
    response = httpx.post(f"{server.url}/v1/uploads", content=seed.stream(recording_id="good-after"), timeout=60)
    assert response.status_code == 200, response.text
    assert response.json()["chunks_new"] == sum(isinstance(e, ArrowMessage) for e in seed.events)
    code, details = server.write_messages(seed.grpc_requests(recording_id="good-after-grpc"))
    assert code == grpc.StatusCode.OK, details


def test_secret_fields_are_never_stored_nor_served(server: LiveServer, seed: Seed) -> None:
    """FLEET_SECRET_FIELDS (default): `ingest_token`, `apiKey`, `DB_PASSWORD` are removed from the
    property chunks before they are written; `tokens_used` is not a secret."""
    response = httpx.post(f"{server.url}/v1/uploads", content=seed.stream(recording_id="secrets"), timeout=60)
    assert response.status_code == 200, response.text
    run = httpx.get(f"{server.url}/v1/runs/secrets", timeout=30).json()
    fleet, db = run["properties"]["fleet"], run["properties"]["db"]
    assert set(fleet) == {"robot_id", "tokens_used", "tags"} and fleet["tokens_used"] == 12
    assert set(db) == {"host"}
    assert run["robot_id"] == "robot-seven-of-nine"
    served = httpx.get(f"{server.url}/v1/runs/secrets/recording.rrd", timeout=60).content
    stored = b"".join(p.read_bytes() for p in Path(server.data_dir).rglob("*") if p.is_file())
    for secret in (b"t0p", b"k3y", b"hunter2", b"ingest_token", b"DB_PASSWORD"):
        assert secret not in served and secret not in stored, secret
    assert b"tokens_used" in served
