"""A TCP forwarder on loopback that a test can make refuse or hang, to play a database that is
down or stuck, or a robot's link that is cut, without touching the real server other tests use.
It counts the bytes it forwards each way (`bytes_up`: client to target)."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager

FORWARD, REFUSE, HANG = "forward", "refuse", "hang"


class TcpProxy:
    def __init__(self, target_host: str, target_port: int) -> None:
        self.target = (target_host, target_port)
        self.mode = FORWARD
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._listener.getsockname()[1])
        self._held: list[socket.socket] = []
        self.bytes_up = 0  # forwarded from clients to the target
        self.bytes_down = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def set_mode(self, mode: str) -> None:
        """Switch mode; connections held by a hang are closed when it ends, as a restart would."""
        with self._lock:
            self.mode = mode
            held, self._held = self._held, []
        if mode != HANG:
            for sock in held:
                with contextlib.suppress(OSError):
                    sock.close()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            with self._lock:
                mode = self.mode
                if mode == HANG:
                    self._held.append(client)  # accepted, never answered
                    continue
            if mode == REFUSE:
                client.close()
                continue
            threading.Thread(target=self._pipe, args=(client,), daemon=True).start()

    def _pipe(self, client: socket.socket) -> None:
        try:
            upstream = socket.create_connection(self.target, timeout=5)
        except OSError:
            client.close()
            return
        with self._lock:
            self._held.append(client)  # so a later hang or refuse cuts it too
            self._held.append(upstream)
        pair = {client: upstream, upstream: client}
        try:
            while True:
                readable, _, _ = select.select(list(pair), [], [], 1.0)
                if self._stop.is_set():
                    return
                with self._lock:
                    if self.mode == HANG:
                        continue  # stop forwarding: the peer waits for an answer that never comes
                for sock in readable:
                    data = sock.recv(65536)
                    if not data:
                        return
                    pair[sock].sendall(data)
                    with self._lock:
                        if sock is client:
                            self.bytes_up += len(data)
                        else:
                            self.bytes_down += len(data)
        except OSError:
            return
        finally:
            for sock in pair:
                with contextlib.suppress(OSError):
                    sock.close()

    def close(self) -> None:
        self._stop.set()
        self._listener.close()
        self.set_mode(REFUSE)


@contextmanager
def tcp_proxy(host: str, port: int) -> Iterator[TcpProxy]:
    proxy = TcpProxy(host, port)
    try:
        yield proxy
    finally:
        proxy.close()
