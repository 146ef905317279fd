"""The load balancer the cluster tests put in front of nodes: a new connection goes to the first
backend that accepts it, in order; one that refuses is passed over; an open connection ends with its
backend, and the client's next one lands on the next backend that answers."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

from tests.balancer import Balancer, balancer, shut


class Echo:
    """A server that answers each line with its name and the line."""

    def __init__(self, name: bytes) -> None:
        self.name = name
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = ("127.0.0.1", int(self.listener.getsockname()[1]))
        self.clients: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return
            self.clients.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            while data := conn.recv(1024):
                conn.sendall(self.name + b":" + data)
        except OSError:
            return

    def close(self) -> None:
        """Gone, as a killed process: the port refuses and open connections end."""
        for sock in [self.listener, *self.clients]:
            shut(sock)


@pytest.fixture
def servers() -> Iterator[tuple[Echo, Echo]]:
    pair = Echo(b"a"), Echo(b"c")
    yield pair
    for server in pair:
        server.close()


def ask(front: Balancer, line: bytes) -> tuple[socket.socket, bytes]:
    conn = socket.create_connection(("127.0.0.1", front.port), timeout=5)
    conn.sendall(line)
    return conn, conn.recv(1024)


def test_connections_go_to_the_first_backend_that_answers(servers: tuple[Echo, Echo]):
    a, c = servers
    with balancer([a.address, c.address]) as front:
        first, answer = ask(front, b"hello")
        assert answer == b"a:hello"
        a.close()
        assert first.recv(1024) == b""  # the open connection ended with its backend
        second, answer = ask(front, b"again")
        assert answer == b"c:again"
        assert front.connections == {a.address: 1, c.address: 1}
        first.close()
        second.close()


def test_no_backend_answering_turns_the_connection_away(servers: tuple[Echo, Echo]):
    a, c = servers
    a.close()
    c.close()
    with balancer([a.address, c.address]) as front:
        conn = socket.create_connection(("127.0.0.1", front.port), timeout=5)
        assert conn.recv(1024) == b""
        conn.close()
        assert front.turned_away == 1
