"""`fleet serve` as a real process on free loopback ports, for end-to-end tests."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import grpc
import httpx

from tests.subprocess_server import ServerProcess, answers_http, free_port
from tests.waiting import T, wait_for

FLEET = str(Path(sys.executable).with_name("fleet"))
WRITE_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"

ROBOT = str(Path(__file__).with_name("robot.py"))


def start_robot(*args: str) -> subprocess.Popen[str]:
    """A robot (robot.py, on the real rerun-sdk) in its own process, driven over its stdin and
    stdout: `start_robot("live", url, copy, run_id)`."""
    robot = subprocess.Popen(
        [sys.executable, ROBOT, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert robot.stdout is not None and robot.stdin is not None
    return robot


class LiveServer:
    def __init__(self, data_dir: Path, **settings: str) -> None:
        self.data_dir = data_dir
        self.http_port, self.grpc_port = free_port(), free_port()
        self.settings = settings
        self.log = data_dir.parent / f"{data_dir.name}-serve.log"
        self.process = ServerProcess(
            [FLEET, "serve"],
            log=self.log,
            name="fleet serve",
            ready=answers_http(f"{self.url}/healthz", lambda r: r.status_code == 200),
        )

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.grpc_port}/proxy"

    @property
    def proc(self) -> subprocess.Popen[bytes]:
        return self.process.proc

    def start(self, timeout: float = 120) -> LiveServer:
        """Start `fleet serve` and wait for its /healthz; the bound is for a CI machine the whole suite
        loads (a start takes 3-6 s of CPU, several starts at once share two cores)."""
        self.process.env = {
            **os.environ,
            "FLEET_DATA_DIR": str(self.data_dir),
            "FLEET_HTTP_ADDR": f"127.0.0.1:{self.http_port}",
            "FLEET_GRPC_ADDR": f"127.0.0.1:{self.grpc_port}",
            **{f"FLEET_{k.upper()}": v for k, v in self.settings.items()},
        }
        self.process.start(timeout)
        return self

    def kill(self) -> None:
        """kill -9: no chance to clean up."""
        self.process.kill()

    def stop(self) -> None:
        self.process.stop()

    @property
    def headers(self) -> dict[str, str]:
        """The admin token's header when auth is on (the token `fleet serve` wrote at its first start)."""
        token_file = self.data_dir / "admin.token"
        return {"Authorization": f"Bearer {token_file.read_text().strip()}"} if token_file.is_file() else {}

    def metric(self, name: str) -> float:
        for line in httpx.get(f"{self.url}/metrics", headers=self.headers, timeout=10).text.splitlines():
            if line.startswith(name + " "):
                return float(line.split()[1])
        raise AssertionError(f"no metric {name}")

    def said(self, lines: int = 15) -> str:
        """The end of the server's log without the access log's lines, for a failure message."""
        text = self.log.read_text(errors="replace") if self.log.is_file() else ""
        return "\n".join([line for line in text.splitlines() if "HTTP/1.1" not in line][-lines:])

    def wait_for(self, predicate: Callable[[], T | None], timeout: float = 60, what: str = "condition") -> T:
        """Wait for `predicate` with a server's patience by default and return what it last gave; a
        failure quotes what the server said."""
        return wait_for(predicate, timeout, what, detail=lambda: f"the server said:\n{self.said()}")

    def healthy(self) -> bool:
        """The process is alive and answers /healthz."""
        if not self.process.running:
            return False
        try:
            return httpx.get(f"{self.url}/healthz", timeout=10).status_code == 200
        except httpx.TransportError:
            return False

    def write_messages(
        self, requests: Iterable[bytes], timeout: float = 60, token: str | None = None
    ) -> tuple[grpc.StatusCode, str]:
        """One WriteMessages call of serialized WriteMessagesRequests, with `token` as its
        `authorization` metadata if given: (status code, details)."""
        metadata = [("authorization", f"Bearer {token}")] if token is not None else None
        with grpc.insecure_channel(f"127.0.0.1:{self.grpc_port}") as channel:
            call = channel.stream_unary(WRITE_MESSAGES, request_serializer=None, response_deserializer=None)
            try:
                call(iter(requests), timeout=timeout, metadata=metadata)
            except grpc.RpcError as exc:
                return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
        return grpc.StatusCode.OK, ""
