"""A small client of the catalog protocol for tests (our generated stubs, with Rerun's headers), and
Rerun's own `rerun server` started on given recordings to compare answers with."""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc

from services.redap.pb import cloud_pb2, cloud_pb2_grpc
from tests.subprocess_server import ServerProcess, free_port
from tests.viewer import native_rerun

CLIENT_VERSION = "rerun-py/0.41.0"


def grpc_answers(port: int) -> bool:
    """The server answers gRPC: a Version call returns (any status but UNAVAILABLE)."""
    with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
        try:
            cloud_pb2_grpc.RerunCloudServiceStub(channel).Version(cloud_pb2.VersionRequest(), timeout=1)
        except grpc.RpcError as exc:
            return bool(exc.code() != grpc.StatusCode.UNAVAILABLE)
    return True


@dataclass
class Redap:
    """A client of a catalog server on `port`: every call carries Rerun's client-version header, the
    token if given, and `x-rerun-entry-id` when `entry` is given."""

    port: int
    token: str | None = None
    client_version: str = CLIENT_VERSION
    channel: grpc.Channel = field(init=False)

    def __post_init__(self) -> None:
        self.channel = grpc.insecure_channel(f"127.0.0.1:{self.port}")
        self.stub = cloud_pb2_grpc.RerunCloudServiceStub(self.channel)

    def metadata(self, entry: str | None = None) -> list[tuple[str, str]]:
        md = [("x-rerun-client-version", self.client_version)]
        if self.token:
            md.append(("authorization", f"Bearer {self.token}"))
        if entry is not None:
            md.append(("x-rerun-entry-id", entry))
        return md

    def call(self, rpc: str, request: Any, entry: str | None = None, timeout: float = 30) -> Any:
        """A unary call's response, or a list of a streaming call's responses."""
        answer = getattr(self.stub, rpc)(request, metadata=self.metadata(entry), timeout=timeout)
        return answer if hasattr(answer, "SerializeToString") else list(answer)

    def close(self) -> None:
        self.channel.close()


@contextmanager
def reference_serving(rerun_bin: str, folder: Path, datasets: Mapping[str, Iterable[Path]]) -> Iterator[Redap]:
    """Rerun's own `rerun server -d NAME=DIR` on copies of the files under `folder` (a dataset per
    name), and a client of it; both closed on leaving."""
    args = []
    for name, files in datasets.items():
        dataset = folder / f"reference-{name}"
        dataset.mkdir(parents=True)
        for path in files:
            shutil.copy(path, dataset / path.name)
        args += ["-d", f"{name}={dataset}"]
    port = free_port()
    server = ServerProcess(
        [native_rerun(rerun_bin), "server", "--host", "127.0.0.1", "-p", str(port), *args],
        log=folder / "reference-server.log",
        ready=lambda: grpc_answers(port),
        name="rerun server",
    )
    server.start(timeout=60)
    client = Redap(port)
    try:
        yield client
    finally:
        client.close()
        server.stop()
