"""Fixtures of the webhooks suites: a receiver on loopback (a small threaded HTTP server that keeps
what it is sent and answers as told), a clock moved by hand, and the webhooks of a node whose
allow-list names that receiver."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from services.settings import load_settings
from services.webhooks.service import Webhooks, webhooks_of
from tests.services.nodes import node_of
from tests.services.retention.conftest import Clock


@dataclass(frozen=True)
class Received:
    path: str
    headers: dict[str, str]
    body: bytes


class Receiver:
    """An endpoint on 127.0.0.1: keeps each POST, answers with the statuses queued in `answers`
    (then 200); a 3xx answer sends a Location elsewhere."""

    def __init__(self) -> None:
        self.got: list[Received] = []
        self.answers: list[int] = []
        self.lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                with receiver.lock:
                    receiver.got.append(Received(self.path, {k.lower(): v for k, v in self.headers.items()}, body))
                    status = receiver.answers.pop(0) if receiver.answers else 200
                self.send_response(status)
                if 300 <= status < 400:
                    self.send_header("Location", "http://169.254.169.254/latest/meta-data/")
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *_: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    endpoint = Receiver()
    yield endpoint
    endpoint.close()


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def hooks(catalog: sessionmaker[Session], clock: Clock, tmp_path: Path, receiver: Receiver) -> Webhooks:
    """The webhooks of a node (auth off: secrets sealed with its key file) that may send to the
    receiver's very host:port, on the test's clock."""
    settings = load_settings(data_dir=tmp_path / "data", scheduler=False, webhook_hosts=[f"127.0.0.1:{receiver.port}"])
    return webhooks_of(node_of(tmp_path, catalog, settings=settings, clock=clock))
