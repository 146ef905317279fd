"""A TCP load balancer on loopback, as a depot's clients meet one in front of several nodes: each new
connection goes to the first backend, in the configured order, that accepts it; a connection lives
and dies with its backend (no retry once bytes have flowed), so a client whose node was killed
reconnects and lands on the next node that answers. It counts the connections each backend took."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

Backend = tuple[str, int]

CONNECT_TIMEOUT_S = 2.0  # a backend that neither accepts nor refuses within this is passed over


class Balancer:
    def __init__(self, backends: Sequence[Backend]) -> None:
        self.backends = list(backends)
        self.connections: dict[Backend, int] = dict.fromkeys(self.backends, 0)  # forwarded, per backend
        self.turned_away = 0  # connections no backend accepted (closed at once)
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._listener.getsockname()[1])
        self._open: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._pipe, args=(client,), daemon=True).start()

    def _connect(self) -> tuple[Backend, socket.socket] | None:
        for backend in list(self.backends):
            try:
                return backend, socket.create_connection(backend, timeout=CONNECT_TIMEOUT_S)
            except OSError:
                continue  # refused or silent: the next backend
        return None

    def _pipe(self, client: socket.socket) -> None:
        found = self._connect()
        if found is None:
            with self._lock:
                self.turned_away += 1
            client.close()
            return
        backend, upstream = found
        upstream.settimeout(None)
        pair = {client: upstream, upstream: client}
        with self._lock:
            self.connections[backend] = self.connections.get(backend, 0) + 1
            self._open.update(pair)
        try:
            while not self._stop.is_set():
                readable, _, _ = select.select(list(pair), [], [], 1.0)
                for sock in readable:
                    data = sock.recv(65536)
                    if not data:
                        return
                    pair[sock].sendall(data)
        except OSError:
            return
        finally:
            with self._lock:
                self._open.difference_update(pair)
            for sock in pair:
                shut(sock)

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            held, self._open = list(self._open), set()
        for sock in [self._listener, *held]:
            shut(sock)


def shut(sock: socket.socket) -> None:
    """Close a socket another thread may be blocked on: close() alone leaves the kernel's socket
    (and a listener's port) open until that call returns; shutdown() ends it at once."""
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        sock.close()


@contextmanager
def balancer(backends: Sequence[Backend]) -> Iterator[Balancer]:
    front = Balancer(backends)
    try:
        yield front
    finally:
        front.close()
