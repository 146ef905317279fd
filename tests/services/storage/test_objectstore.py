"""One behaviour suite for every object-store backend: a local folder, S3 via moto (in-process),
and a real S3-compatible server (SeaweedFS) started on loopback."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.sealed.tiers import open_tiers
from services.settings import load_settings
from services.storage.objectstore import (
    STREAM_PIECE_BYTES,
    ObjectNotFoundError,
    ObjectStore,
    StorageError,
    check_key,
    open_store,
    supports_streaming,
)
from services.storage.s3 import S3Store
from tests.services.storage.s3_backends import REGION, S3_BACKENDS, s3_target_for


@pytest.fixture(params=["file", *S3_BACKENDS])
def store(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[ObjectStore]:
    if request.param == "file":
        yield open_store((tmp_path / "warm").as_uri())
        return
    for target in s3_target_for(request.param, request, tmp_path, monkeypatch):
        yield open_store(target.url, endpoint_url=target.endpoint_url, region=REGION)


def test_put_get_head_delete(store: ObjectStore):
    info = store.put("robot-7/2026-11-21/run-1/run.json", b'{"id": "run-1"}')
    assert info.size == 15 and info.key == "robot-7/2026-11-21/run-1/run.json"
    assert store.get_range(info.key) == b'{"id": "run-1"}'
    assert store.head(info.key).size == 15
    store.delete(info.key)
    with pytest.raises(ObjectNotFoundError, match=r"run\.json"):
        store.head(info.key)
    store.delete(info.key)  # deleting twice is fine: deletes are retried


def test_ranges(store: ObjectStore):
    data = os.urandom(10_000)
    store.put("a/b.bin", data)
    assert store.get_range("a/b.bin", 100, 50) == data[100:150]
    assert store.get_range("a/b.bin", 9_990) == data[9_990:]
    assert store.get_range("a/b.bin", 0, 0) == b""
    with pytest.raises(ObjectNotFoundError):
        store.get_range("a/missing.bin", 0, 10)


def test_a_stream_reads_what_ranges_read_in_bounded_pieces(store: ObjectStore):
    data = os.urandom(2 * STREAM_PIECE_BYTES + 12_345)
    store.put("a/big.bin", io.BytesIO(data))
    assert supports_streaming(store)
    pieces = list(store.stream("a/big.bin"))
    assert b"".join(pieces) == data and max(len(p) for p in pieces) <= STREAM_PIECE_BYTES
    assert b"".join(store.stream("a/big.bin", 100, 50)) == data[100:150]
    assert b"".join(store.stream("a/big.bin", len(data) - 10)) == data[-10:]
    assert b"".join(store.stream("a/big.bin", 5, 0)) == b""
    with pytest.raises(ObjectNotFoundError):
        b"".join(store.stream("a/missing.bin"))


def test_put_from_a_file_and_replace(store: ObjectStore):
    big = os.urandom(3 * 1024 * 1024)
    assert store.put("x/big.rrd", io.BytesIO(big)).size == len(big)
    assert store.get_range("x/big.rrd", len(big) - 10) == big[-10:]
    store.put("x/big.rrd", b"smaller")
    assert store.get_range("x/big.rrd") == b"smaller"


def test_list_by_prefix_in_key_order(store: ObjectStore):
    for key in ("r2/2026-11-21/b/run.json", "r1/2026-11-21/a/run.json", "r1/2026-11-22/c/run.json"):
        store.put(key, b"{}")
    assert [o.key for o in store.list("r1/")] == ["r1/2026-11-21/a/run.json", "r1/2026-11-22/c/run.json"]
    assert len(list(store.list())) == 3
    assert list(store.list("nothing/")) == []


@pytest.mark.parametrize("key", ["", "/abs", "a/../b", "a b", "a\\b"])
def test_unsafe_keys_are_refused(key: str):
    with pytest.raises(ValueError, match="object key"):
        check_key(key)


def test_unknown_scheme():
    with pytest.raises(StorageError, match="file:///PATH or s3://BUCKET/PREFIX"):
        open_store("ftp://x/y")


def test_s3_uploads_take_the_part_size_and_concurrency_of_the_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    """What an upload holds in memory is set by FLEET_S3_PART_BYTES x FLEET_S3_UPLOAD_CONCURRENCY."""
    monkeypatch.setenv("FLEET_S3_PART_BYTES", str(8 * 1024 * 1024))
    monkeypatch.setenv("FLEET_S3_UPLOAD_CONCURRENCY", "3")
    monkeypatch.setenv("FLEET_WARM_URL", "s3://fleet/warm")
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    tiers = open_tiers(load_settings())
    assert isinstance(tiers.warm, S3Store)
    transfer = tiers.warm._transfer
    assert (transfer.multipart_chunksize, transfer.max_request_concurrency) == (8 * 1024 * 1024, 3)
    monkeypatch.setenv("FLEET_S3_PART_BYTES", "1024")
    with pytest.raises(ValueError, match="s3_part_bytes"):
        load_settings()
