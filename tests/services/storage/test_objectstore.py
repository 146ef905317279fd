"""One behaviour suite for every object-store backend: a local folder, S3 via moto (in-process),
and a real S3-compatible server (SeaweedFS) started on loopback."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.storage.objectstore import ObjectNotFoundError, ObjectStore, StorageError, check_key, open_store
from tests.seaweedfs import seaweedfs

BUCKET = "fleet-warm"


@pytest.fixture(scope="module")
def seaweed_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    import boto3

    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as endpoint:
        # One bucket, a prefix per test: each SeaweedFS bucket reserves volumes of its own.
        boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1", aws_access_key_id="test",
                     aws_secret_access_key="test").create_bucket(Bucket=BUCKET)
        yield endpoint


@pytest.fixture(params=["file", "s3-moto",
                        pytest.param("s3-seaweedfs", marks=[pytest.mark.s3server, pytest.mark.slow])])
def store(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[ObjectStore]:
    if request.param == "file":
        yield open_store((tmp_path / "warm").as_uri())
        return
    for name, value in (("AWS_ACCESS_KEY_ID", "test"), ("AWS_SECRET_ACCESS_KEY", "test"),
                        ("AWS_DEFAULT_REGION", "us-east-1")):
        monkeypatch.setenv(name, value)
    if request.param == "s3-seaweedfs":
        endpoint = request.getfixturevalue("seaweed_endpoint")
        yield open_store(f"s3://{BUCKET}/{tmp_path.name}", endpoint_url=endpoint, region="us-east-1")
        return
    from moto import mock_aws

    with mock_aws():
        import boto3

        boto3.client("s3", region_name="us-east-1").create_bucket(Bucket="fleet-warm")
        yield open_store("s3://fleet-warm/depot", region="us-east-1")


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
