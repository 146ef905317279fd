"""S3 and S3-compatible object storage (the only module that imports boto3)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import ssl
import threading
import urllib.request
from collections.abc import AsyncIterator, Iterator
from typing import Any, BinaryIO
from urllib.parse import urlparse

import boto3
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError
from botocore.httpsession import get_cert_path

from core.errors import ConflictError
from services.storage import loop_get
from services.storage.objectstore import (
    PRESIGNED_TTL_MAX_S,
    STREAM_PIECE_BYTES,
    ObjectInfo,
    ObjectNotFoundError,
    StorageError,
    Uploads,
    check_key,
)
from services.storage.readahead import READ_THREADS
from services.storage.splice import Source

# Verified by the server on every put and part: a body damaged on the way is refused. CRC32, as
# botocore and AWS's SDKs default to: it catches transmission damage as well as a digest does, needs
# no extra package (CRC32C and CRC64NVME need awscrt), and costs a fraction of SHA-256, which
# promotion's profile showed as a seventh of its CPU. (What a sealed run *is* is the SHA-256 the
# sealing computes and the catalog keeps.) A multipart object gets a composite checksum ("...-N"):
# each part was verified on arrival and the completion names every part's checksum.
CHECKSUM_ALGORITHM = "CRC32"
# Short connect timeout: during an outage callers learn quickly and retry on their own schedule.
CONNECT_TIMEOUT_S = 5
READ_TIMEOUT_S = 60  # a store that sends nothing this long is given up (botocore and reads on the loop)


class S3Store:
    def __init__(
        self,
        url: str,
        *,
        endpoint_url: str | None = None,
        region: str | None = None,
        uploads: Uploads | None = None,
        presign_endpoint_url: str | None = None,
        loop_reads: bool = True,
    ) -> None:
        uploads = uploads or Uploads()
        parsed = urlparse(url)
        if not parsed.netloc:
            raise StorageError(f"{url!r} names no bucket: use s3://BUCKET/PREFIX")
        self.url = url
        self.bucket = parsed.netloc
        self.prefix = parsed.path.strip("/")
        self._session = boto3.session.Session(region_name=region)
        self.endpoint_url = endpoint_url
        self._client: Any = self._session.client(
            "s3",
            endpoint_url=endpoint_url,
            config=Config(
                retries={"max_attempts": 3, "mode": "standard"},
                connect_timeout=CONNECT_TIMEOUT_S,
                read_timeout=READ_TIMEOUT_S,
                # Downloads keep several ranged reads under way (up to READ_THREADS at once in a
                # process), uploads several parts: each needs a connection of its own.
                max_pool_connections=READ_THREADS + uploads.concurrency,
                # A body is checked by its CRC32 (CHECKSUM_ALGORITHM), not hashed again for the
                # signature: botocore skips that SHA-256 over https already, and over http:// it
                # costs a promotion 0.8 s of CPU per GB (a sixth of the depot's share) for no check
                # the CRC32 does not make; the signature still covers the headers, the CRC32 among
                # them. (An http:// link to the store is for a network one trusts: it is not encrypted.)
                s3={"payload_signing_enabled": False},
            ),
        )
        self._transfer = TransferConfig(
            multipart_threshold=uploads.part_bytes,
            multipart_chunksize=uploads.part_bytes,
            max_concurrency=uploads.concurrency,
        )
        # Parts read ahead of a stream being uploaded (a run sealed into the store as it is made):
        # s3transfer's default holds 10 whatever the concurrency.
        self._transfer.max_in_memory_upload_chunks = uploads.concurrency
        self._presign_endpoint_url = presign_endpoint_url or endpoint_url
        self._signers: dict[str | None, Any] = {}  # by endpoint: clients that sign URLs (_signer)
        self._signers_lock = threading.Lock()
        self._tls: ssl.SSLContext | None = None
        # botocore goes through a proxy where the environment names one; a read on the loop does not
        self.loop_reads = loop_reads and not _proxied(endpoint_url or "https://s3.amazonaws.com")

    def access(self) -> dict[str, Any]:
        """Credentials, region and endpoint, for other readers of this store (analytics SQL)."""
        credentials = self._session.get_credentials()
        frozen = credentials.get_frozen_credentials() if credentials is not None else None
        endpoint = urlparse(self.endpoint_url) if self.endpoint_url else None
        return {
            "key_id": frozen.access_key if frozen else None,
            "secret": frozen.secret_key if frozen else None,
            "session_token": frozen.token if frozen else None,
            "region": self._client.meta.region_name or "us-east-1",
            "endpoint": endpoint.netloc if endpoint else None,
            "use_ssl": endpoint.scheme != "http" if endpoint else True,
        }

    def _key(self, key: str) -> str:
        check_key(key)
        return f"{self.prefix}/{key}" if self.prefix else key

    def _relative(self, full: str) -> str:
        return full[len(self.prefix) + 1 :] if self.prefix else full

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        """Upload with a SHA-256 checksum of the body (of each part, for a multipart upload) that
        botocore computes from the bytes it sends and the server verifies before storing: a body
        that arrives different is refused (BadDigest) and nothing is stored. The ETag is not looked
        at: it is the MD5 of the body only without SSE-KMS, and no MD5 at all with it."""
        try:
            if isinstance(data, bytes | bytearray | memoryview):
                body = bytes(data)
                self._client.put_object(
                    Bucket=self.bucket, Key=self._key(key), Body=body, ChecksumAlgorithm=CHECKSUM_ALGORITHM
                )
                sent = len(body)
            else:  # multipart above the part size
                reader = _Counting(data)
                self._client.upload_fileobj(
                    reader,
                    self.bucket,
                    self._key(key),
                    Config=self._transfer,
                    ExtraArgs={"ChecksumAlgorithm": CHECKSUM_ALGORITHM},
                )
                sent = reader.size
        except (ClientError, BotoCoreError) as exc:
            raise StorageError(f"cannot write {key!r} to {self.url}: {exc}") from exc
        info = self.head(key)
        if info.size != sent:  # a server that ignored the checksum and kept part of the body
            self.delete(key)
            raise StorageError(
                f"upload of {key!r} to {self.url} does not match what was sent "
                f"({info.size} bytes stored, {sent} sent): retry"
            )
        return info

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        wanted = _range(start, length)
        if length == 0:
            return b""
        try:
            body: bytes = self._client.get_object(Bucket=self.bucket, Key=self._key(key), Range=wanted)["Body"].read()
            return body
        except ClientError as exc:
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot read {key!r} from {self.url}: {exc}") from exc

    def stream(self, key: str, start: int = 0, length: int | None = None) -> Iterator[bytes]:
        """One GET of the range, its body read in pieces: the store sends it as it sends any object
        (a whole download read this way costs SeaweedFS a third less CPU than ranged GETs of 16 MiB)."""
        if length == 0:
            return
        ranged = {} if start == 0 and length is None else {"Range": _range(start, length)}
        try:
            body = self._client.get_object(Bucket=self.bucket, Key=self._key(key), **ranged)["Body"]
        except ClientError as exc:
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot read {key!r} from {self.url}: {exc}") from exc
        try:
            yield from body.iter_chunks(STREAM_PIECE_BYTES)
        except BotoCoreError as exc:  # the connection broke mid-way (urllib3's errors come wrapped)
            raise StorageError(f"reading {key!r} from {self.url} broke off: {exc}") from exc
        finally:
            body.close()

    async def loop_read(self, key: str, start: int, length: int) -> AsyncIterator[memoryview]:
        """One GET of `key` from `start`, read on the event loop (services/storage/loop_get.py),
        signed for this read alone: the request carries a signature good for READ_URL_TTL_S, never
        a credential."""
        url, tls = await asyncio.to_thread(self._signed_read, key)
        async for piece in loop_get.get(url, start, length, self._reading(key, tls)):
            yield piece

    def loop_splices(self) -> bool:
        return self.loop_reads and loop_get.spliceable(self.endpoint_url or "https:")

    @contextlib.asynccontextmanager
    async def loop_open(self, key: str, start: int, length: int) -> AsyncIterator[Source]:
        """As `loop_read`, its body left in the socket to be spliced to a client (plain HTTP only)."""
        url, tls = await asyncio.to_thread(self._signed_read, key)
        async with loop_get.opened(url, start, length, self._reading(key, tls)) as source:
            yield source

    def _reading(self, key: str, tls: ssl.SSLContext | None) -> loop_get.Reading:
        what = f"{key!r} from {self.url}"
        return loop_get.Reading(what, connect_timeout_s=CONNECT_TIMEOUT_S, read_timeout_s=READ_TIMEOUT_S, tls=tls)

    def _signed_read(self, key: str) -> tuple[str, ssl.SSLContext | None]:
        # signed for the depot's own endpoint, not the one clients reach
        url: str = self._signer(self.endpoint_url).generate_presigned_url(
            "get_object", Params={"Bucket": self.bucket, "Key": self._key(key)}, ExpiresIn=READ_URL_TTL_S
        )
        if url.startswith("https:") and self._tls is None:
            # the certificates botocore trusts (AWS_CA_BUNDLE, else its bundle), not only the system's
            self._tls = ssl.create_default_context(cafile=os.environ.get("AWS_CA_BUNDLE") or get_cert_path(True))
        return url, self._tls

    def presigned_get(self, key: str, expires_s: int) -> str:
        """A SigV4 query-signed GET of `key` (signed offline: no call to the store). Only the host
        is signed, so a client may add its own Range header."""
        if not 0 < expires_s <= PRESIGNED_TTL_MAX_S:
            raise ValueError(f"a presigned URL lasts 1 to {PRESIGNED_TTL_MAX_S} s, not {expires_s}")
        url: str = self._signer(self._presign_endpoint_url).generate_presigned_url(
            "get_object", Params={"Bucket": self.bucket, "Key": self._key(key)}, ExpiresIn=expires_s
        )
        return url

    def _signer(self, endpoint_url: str | None) -> Any:
        """A client that signs URLs for `endpoint_url`, made once: SigV4 (botocore's default for
        presigning S3 is not SigV4 in every region), addressing buckets as the depot's client does.
        Made under a lock: a boto3 session is not safe to make clients from several threads at once."""
        with self._signers_lock:
            if endpoint_url not in self._signers:
                self._signers[endpoint_url] = self._session.client(
                    "s3",
                    endpoint_url=endpoint_url,
                    region_name=self._client.meta.region_name,
                    config=Config(signature_version="s3v4", s3=self._client.meta.config.s3),
                )
            return self._signers[endpoint_url]

    def head(self, key: str) -> ObjectInfo:
        try:
            answer = self._client.head_object(Bucket=self.bucket, Key=self._key(key))
        except ClientError as exc:
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot reach {self.url}: {exc}") from exc
        restore = answer.get("Restore")
        state = None if restore is None else "ongoing" if 'ongoing-request="true"' in restore else "restored"
        return ObjectInfo(
            key,
            int(answer["ContentLength"]),
            answer["LastModified"],
            answer.get("StorageClass"),
            state,
            answer.get("ETag", "").strip('"') or None,
        )

    def set_storage_class(self, key: str, storage_class: str) -> ObjectInfo:
        """Move an object to another storage class in place (a copy onto itself)."""
        full = self._key(key)
        try:
            self._client.copy_object(
                Bucket=self.bucket,
                Key=full,
                CopySource={"Bucket": self.bucket, "Key": full},
                StorageClass=storage_class,
                MetadataDirective="COPY",
            )
        except ClientError as exc:
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot reach {self.url}: {exc}") from exc
        return self.head(key)

    def restore(self, key: str, days: int) -> None:
        try:
            self._client.restore_object(Bucket=self.bucket, Key=self._key(key), RestoreRequest={"Days": days})
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") == "RestoreAlreadyInProgress":
                return
            raise self._error(key, exc) from exc
        except BotoCoreError as exc:
            raise StorageError(f"cannot reach {self.url}: {exc}") from exc

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        full = self._key(prefix) if prefix else (self.prefix + "/" if self.prefix else "")
        try:
            for page in self._client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=full):
                for item in page.get("Contents", []):
                    yield ObjectInfo(
                        self._relative(item["Key"]), int(item["Size"]), item["LastModified"], item.get("StorageClass")
                    )
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
        if code == "InvalidObjectState":
            return ConflictError(f"{key!r} in {self.url} is archived: restore it before reading")
        return StorageError(f"{self.url}: {key!r}: {code or exc}")


FleetErrorLike = ObjectNotFoundError | StorageError | ConflictError
READ_URL_TTL_S = 60  # a read on the loop sends its request at once; a resumed one is signed again


def _proxied(endpoint_url: str) -> bool:
    """Whether the environment sends requests to `endpoint_url` through a proxy (HTTPS_PROXY, ...)."""
    parsed = urlparse(endpoint_url)
    proxies = urllib.request.getproxies()
    return parsed.scheme in proxies and not urllib.request.proxy_bypass(parsed.hostname or "")


def _range(start: int, length: int | None) -> str:
    return f"bytes={start}-" if length is None else f"bytes={start}-{start + length - 1}"


class _Counting:
    """A file read once, front to back, by the uploader, counting the bytes it gave."""

    def __init__(self, fh: BinaryIO) -> None:
        self._fh, self.size = fh, 0

    def read(self, n: int = -1) -> bytes:
        data = self._fh.read(n)
        self.size += len(data)
        return data
