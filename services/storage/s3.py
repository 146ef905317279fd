"""S3 and S3-compatible object storage (the only module that imports boto3)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, BinaryIO
from urllib.parse import urlparse

import boto3
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

from services.storage.objectstore import ObjectInfo, ObjectNotFoundError, StorageError, check_key

MULTIPART_BYTES = 64 * 1024 * 1024


class S3Store:
    def __init__(self, url: str, *, endpoint_url: str | None = None, region: str | None = None) -> None:
        parsed = urlparse(url)
        if not parsed.netloc:
            raise StorageError(f"{url!r} names no bucket: use s3://BUCKET/PREFIX")
        self.url = url
        self.bucket = parsed.netloc
        self.prefix = parsed.path.strip("/")
        self._client: Any = boto3.client("s3", endpoint_url=endpoint_url, region_name=region,
                                         config=Config(retries={"max_attempts": 5, "mode": "standard"}))
        self._transfer = TransferConfig(multipart_threshold=MULTIPART_BYTES, multipart_chunksize=MULTIPART_BYTES)

    def _key(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _relative(self, full: str) -> str:
        return full[len(self.prefix) + 1:] if self.prefix else full

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        try:
            if isinstance(data, bytes | bytearray | memoryview):
                self._client.put_object(Bucket=self.bucket, Key=self._key(key), Body=bytes(data))
            else:  # multipart above MULTIPART_BYTES
                self._client.upload_fileobj(data, self.bucket, self._key(key), Config=self._transfer)
        except (ClientError, BotoCoreError) as exc:
            raise StorageError(f"cannot write {key!r} to {self.url}: {exc}") from exc
        return self.head(key)

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        wanted = f"bytes={start}-" if length is None else f"bytes={start}-{start + length - 1}"
        if length == 0:
            return b""
        try:
            body: bytes = self._client.get_object(Bucket=self.bucket, Key=self._key(key), Range=wanted)["Body"].read()
            return body
        except ClientError as exc:
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot read {key!r} from {self.url}: {exc}") from exc

    def head(self, key: str) -> ObjectInfo:
        try:
            answer = self._client.head_object(Bucket=self.bucket, Key=self._key(key))
        except ClientError as exc:
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot reach {self.url}: {exc}") from exc
        return ObjectInfo(key, int(answer["ContentLength"]), answer["LastModified"], answer.get("StorageClass"))

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        full = self._key(prefix) if prefix else (self.prefix + "/" if self.prefix else "")
        try:
            for page in self._client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=full):
                for item in page.get("Contents", []):
                    yield ObjectInfo(self._relative(item["Key"]), int(item["Size"]), item["LastModified"],
                                     item.get("StorageClass"))
        except (ClientError, BotoCoreError) as exc:
            raise StorageError(f"cannot list {self.url}: {exc}") from exc

    def delete(self, key: str) -> None:
        try:
            self._client.delete_object(Bucket=self.bucket, Key=self._key(key))
        except (ClientError, BotoCoreError) as exc:
            raise StorageError(f"cannot delete {key!r} from {self.url}: {exc}") from exc

    def _error(self, key: str, exc: ClientError) -> FleetErrorLike:
        code = exc.response.get("Error", {}).get("Code", "")
        if code in ("404", "NoSuchKey", "NotFound"):
            return ObjectNotFoundError(f"no object {key!r} in {self.url}")
        return StorageError(f"{self.url}: {key!r}: {code or exc}")


FleetErrorLike = ObjectNotFoundError | StorageError
