"""Uploads to S3 are checked by the server with a CRC32 checksum (botocore's flexible checksums),
not by comparing the ETag to an MD5: with SSE-KMS the ETag is no MD5, and a good upload must not be
taken for a corrupted one. A body corrupted on the way is still refused."""

from __future__ import annotations

import base64
import hashlib
import io
import os
import zlib
from typing import Any

import boto3
import pytest

from services.storage import s3
from services.storage.objectstore import ObjectNotFoundError, StorageError, Uploads, open_store
from tests.services.storage.s3_backends import BUCKET, REGION, S3Target

PART = 5 * 1024 * 1024  # S3's smallest part
SIZES = {"single": 10_000, "multipart": 2 * PART + 123}  # a multipart body is given as a file


def _open(target: S3Target, monkeypatch: pytest.MonkeyPatch) -> s3.S3Store:
    store = open_store(target.url, endpoint_url=target.endpoint_url, region=REGION, uploads=Uploads(part_bytes=PART))
    assert isinstance(store, s3.S3Store)
    return store


def _put(store: s3.S3Store, key: str, data: bytes, shape: str) -> Any:
    return store.put(key, data if shape == "single" else io.BytesIO(data))


def _client(target: S3Target) -> Any:
    return boto3.client("s3", endpoint_url=target.endpoint_url, region_name=REGION)


def _crc32(data: bytes) -> str:
    return base64.b64encode(zlib.crc32(data).to_bytes(4, "big")).decode()


@pytest.mark.parametrize("shape", SIZES)
def test_an_upload_whose_etag_is_not_the_md5_is_kept(s3_target: S3Target, monkeypatch: pytest.MonkeyPatch, shape: str):
    """What an SSE-KMS bucket answers: an object's ETag (after a put, a multipart upload, in a head)
    is 32 hex digits that are not the body's MD5. The upload is good and must be reported stored,
    not deleted. (Parts' ETags are left: the server is handed them back to complete the upload.)"""
    store = _open(s3_target, monkeypatch)
    kms_etag = hashlib.md5(b"encrypted with a KMS key", usedforsecurity=False).hexdigest()

    def etag_is_not_the_md5(parsed: dict[str, Any], **_: object) -> None:
        if "ETag" in parsed:
            parsed["ETag"] = f'"{kms_etag}"'

    for operation in ("PutObject", "CompleteMultipartUpload", "HeadObject"):
        store._client.meta.events.register(f"after-call.s3.{operation}", etag_is_not_the_md5)
    data = os.urandom(SIZES[shape])
    info = _put(store, "r/recording.rrd", data, shape)
    assert info.etag == kms_etag != hashlib.md5(data, usedforsecurity=False).hexdigest()  # the rewrite was seen
    assert info.size == len(data)
    assert store.head("r/recording.rrd").size == len(data), "a good upload was deleted: its ETag is no MD5"
    assert store.get_range("r/recording.rrd") == data


@pytest.mark.parametrize("shape", SIZES)
def test_uploads_carry_a_crc32_checksum(s3_target: S3Target, monkeypatch: pytest.MonkeyPatch, shape: str):
    """The checksum the server checks is CRC32: of the body, or for a multipart upload of the parts'
    checksums ("-N" on servers that mark it composite), or of the whole object on servers that
    combine them."""
    store = _open(s3_target, monkeypatch)
    data = os.urandom(SIZES[shape])
    _put(store, "r/recording.rrd", data, shape)
    stored = _client(s3_target).head_object(Bucket=BUCKET, Key=store._key("r/recording.rrd"), ChecksumMode="ENABLED")
    if shape == "single":
        assert stored.get("ChecksumCRC32") == _crc32(data)
    else:
        parts = [data[i : i + PART] for i in range(0, len(data), PART)]
        composite = _crc32(b"".join(zlib.crc32(p).to_bytes(4, "big") for p in parts))
        assert stored.get("ChecksumCRC32") in (composite, f"{composite}-{len(parts)}", _crc32(data))


def _corrupt_after_checksum(request: Any, **_: object) -> None:
    """Flip a byte of the body after botocore computed its checksum and before it is signed: what
    the server sees is a body damaged on the way that the signature alone would not catch."""
    body = request.data if isinstance(request.data, bytes | bytearray) else request.data.read()
    request.data = bytes([body[0] ^ 0xFF]) + bytes(body[1:])


@pytest.mark.s3server
@pytest.mark.slow  # starts SeaweedFS
@pytest.mark.parametrize("s3_target", ["s3-seaweedfs"], indirect=True)  # moto keeps any checksum it is sent
@pytest.mark.parametrize("shape", SIZES)
def test_a_body_corrupted_on_the_way_is_refused(s3_target: S3Target, monkeypatch: pytest.MonkeyPatch, shape: str):
    """The guarantee the MD5 comparison gave, kept: the server compares the body it received with
    the checksum and refuses it, so nothing is stored and an object it would replace is left as it was."""
    store = _open(s3_target, monkeypatch)
    store.put("r/kept.rrd", b"the previous version")
    store._client.meta.events.register("before-sign.s3.PutObject", _corrupt_after_checksum)
    store._client.meta.events.register("before-sign.s3.UploadPart", _corrupt_after_checksum)
    data = os.urandom(SIZES[shape])
    for key in ("r/new.rrd", "r/kept.rrd"):
        with pytest.raises(StorageError, match=r"\(BadDigest\)"):
            _put(store, key, data, shape)
    with pytest.raises(ObjectNotFoundError):
        store.head("r/new.rrd")
    assert store.get_range("r/kept.rrd") == b"the previous version"


@pytest.mark.parametrize("shape", SIZES)
def test_a_body_is_checked_by_its_checksum_not_hashed_for_the_signature(
    s3_target: S3Target, monkeypatch: pytest.MonkeyPatch, shape: str
):
    """Over http:// too, a body goes with its CRC32 and an unsigned payload (botocore would hash it
    with SHA-256 for the signature, a second pass over every byte a promotion sends): the request
    is still signed, and the server stores the body whole."""
    store = _open(s3_target, monkeypatch)
    sent: list[dict[str, bytes]] = []

    def seen(request: Any, **_: object) -> None:
        sent.append({name.lower(): value for name, value in request.headers.items()})

    for operation in ("PutObject", "UploadPart"):
        store._client.meta.events.register(f"before-send.s3.{operation}", seen)
    data = os.urandom(SIZES[shape])
    _put(store, "r/recording.rrd", data, shape)
    for headers in sent:
        # over http:// the checksum is a header; over https:// (moto's endpoint) a trailer of the body
        assert headers["x-amz-content-sha256"] in (b"UNSIGNED-PAYLOAD", b"STREAMING-UNSIGNED-PAYLOAD-TRAILER")
        assert headers.get("x-amz-checksum-crc32") or headers.get("x-amz-trailer") == b"x-amz-checksum-crc32"
        assert b"Signature=" in headers["authorization"]
    assert len(sent) == (1 if shape == "single" else 3)
    assert store.get_range("r/recording.rrd") == data
