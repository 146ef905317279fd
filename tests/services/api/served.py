"""An ASGI app served by uvicorn with the REST port's protocol, in a thread of the test's process, on
a free loopback port: the real HTTP server in front of an app the test holds (for what only a real
server does, such as splicing into a client's connection)."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator
from typing import Any

import uvicorn

from services.api.http_protocol import BoundedHttpToolsProtocol
from tests.waiting import wait_for


@contextlib.contextmanager
def served(app: Any) -> Iterator[str]:
    """`app` behind uvicorn with BoundedHttpToolsProtocol; yields its base URL."""
    listener = socket.create_server(("127.0.0.1", 0))
    config = uvicorn.Config(app, http=BoundedHttpToolsProtocol, lifespan="off", log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    try:
        wait_for(lambda: server.started or not thread.is_alive(), timeout=30, what="uvicorn to start")
        assert thread.is_alive(), "uvicorn stopped at its start"
        yield f"http://127.0.0.1:{listener.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        listener.close()
