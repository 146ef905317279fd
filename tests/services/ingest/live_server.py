"""`fleet serve` as a real process on free loopback ports, for end-to-end tests."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import grpc
import httpx

FLEET = str(Path(sys.executable).with_name("fleet"))
WRITE_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    def __init__(self, data_dir: Path, **settings: str) -> None:
        self.data_dir = data_dir
        self.http_port, self.grpc_port = free_port(), free_port()
        self.settings = settings
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = data_dir.parent / f"{data_dir.name}-serve.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def grpc_url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.grpc_port}/proxy"

    def start(self, timeout: float = 60) -> LiveServer:
        env = {**os.environ, "FLEET_DATA_DIR": str(self.data_dir),
               "FLEET_HTTP_ADDR": f"127.0.0.1:{self.http_port}", "FLEET_GRPC_ADDR": f"127.0.0.1:{self.grpc_port}",
               **{f"FLEET_{k.upper()}": v for k, v in self.settings.items()}}
        log = open(self.log, "ab")  # noqa: SIM115 - the server process writes it
        self.proc = subprocess.Popen([FLEET, "serve"], env=env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"fleet serve exited: {self.log.read_text()[-3000:]}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return self
            except httpx.TransportError:
                time.sleep(0.05)  # polling for the condition, bounded by the deadline
        raise AssertionError(f"fleet serve did not answer within {timeout}s")

    def kill(self) -> None:
        """kill -9: no chance to clean up."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def metric(self, name: str) -> float:
        for line in httpx.get(f"{self.url}/metrics", timeout=10).text.splitlines():
            if line.startswith(name + " "):
                return float(line.split()[1])
        raise AssertionError(f"no metric {name}")

    def wait_for(self, predicate: object, timeout: float = 60, what: str = "condition") -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():  # type: ignore[operator]
                return
            time.sleep(0.1)  # polling for the condition, bounded by the deadline
        raise AssertionError(f"timed out waiting for {what}")

    def healthy(self) -> bool:
        """The process is alive and answers /healthz."""
        if self.proc is None or self.proc.poll() is not None:
            return False
        try:
            return httpx.get(f"{self.url}/healthz", timeout=10).status_code == 200
        except httpx.TransportError:
            return False

    def write_messages(self, requests: list[bytes], timeout: float = 60) -> tuple[grpc.StatusCode, str]:
        """One WriteMessages call of serialized WriteMessagesRequests: (status code, details)."""
        with grpc.insecure_channel(f"127.0.0.1:{self.grpc_port}") as channel:
            call = channel.stream_unary(WRITE_MESSAGES, request_serializer=None, response_deserializer=None)
            try:
                call(iter(requests), timeout=timeout)
            except grpc.RpcError as exc:
                return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
        return grpc.StatusCode.OK, ""
