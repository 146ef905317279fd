"""The least a relay between the store and the client can cost on this machine, for context beside
`benchmarks/serve.py --tier warm`: one thread per request that sends the store's GET of a presigned
URL on to the client (`recv_into` one reused buffer, `sendall`), with no HTTP server, framework or
event loop. What it reaches beside the store's own GET is what any server in the middle can hope
for when the store, the relay and the client share the same cores."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator
from urllib.parse import urlsplit

BUFFER_BYTES = 1 << 20


def _store_get(url: str) -> tuple[socket.socket, int]:
    """A GET of `url` sent on a socket of its own, its head read: (the socket at the body, its length)."""
    parts = urlsplit(url)
    assert parts.hostname is not None
    sock = socket.create_connection((parts.hostname, parts.port or 80))
    sock.sendall(
        f"GET {parts.path}?{parts.query} HTTP/1.1\r\nHost: {parts.netloc}\r\nConnection: close\r\n\r\n".encode()
    )
    head = b""
    while True:  # peek, then take exactly the head: the body stays in the socket
        seen = sock.recv(65536, socket.MSG_PEEK)
        end = seen.find(b"\r\n\r\n")
        if end >= 0:
            head += sock.recv(end + 4)
            break
        head += sock.recv(len(seen))
    length = next(
        int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length")
    )
    return sock, length


def _relay(listener: socket.socket, url: str) -> None:
    buffer = bytearray(BUFFER_BYTES)
    view = memoryview(buffer)
    while True:
        try:
            client, _ = listener.accept()
        except OSError:
            return  # the listener was closed
        with client:
            client.recv(65536)  # the client's request (curl's is one small packet)
            store, left = _store_get(url)
            with store:
                client.sendall(f"HTTP/1.1 200 OK\r\nContent-Length: {left}\r\nConnection: close\r\n\r\n".encode())
                while left:
                    got = store.recv_into(view, min(left, BUFFER_BYTES))
                    if not got:
                        break
                    client.sendall(view[:got])
                    left -= got


@contextlib.contextmanager
def bare_relay(url: str) -> Iterator[str]:
    """A bare relay of the object at the presigned `url` on a free loopback port; yields its URL."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    thread = threading.Thread(target=_relay, args=(listener, url), daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{listener.getsockname()[1]}/"
    finally:
        listener.close()
