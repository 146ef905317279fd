"""What `fleet serve` claims before it starts: the data dir and its two ports, each refused in one line."""

from __future__ import annotations

import asyncio
import os
import socket
from pathlib import Path

import pytest

from core.errors import ConflictError
from services.startup import hold_data_dir, listen_grpc, listen_http, private_socket_path, release_private_socket
from tests.waiting import wait_for_async


def test_the_data_dir_is_held_once_and_released_after(tmp_path: Path):
    refused = pytest.raises(ConflictError, match=rf"\(PID {os.getpid()}\).*--data-dir or FLEET_DATA_DIR")
    with hold_data_dir(tmp_path / "data"), refused, hold_data_dir(tmp_path / "data"):
        pass
    with hold_data_dir(tmp_path / "data"):  # free again: the lock went with the first holder
        pass


def test_a_port_someone_listens_on_is_refused_for_http_and_grpc():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(
            ConflictError,
            match=rf"REST API address 127\.0\.0\.1:{port} is already in use .*: "
            r"set another with --http-addr or FLEET_HTTP_ADDR",
        ):
            listen_http("127.0.0.1", port)
        with pytest.raises(
            ConflictError,
            match=rf"Rerun gRPC address 0\.0\.0\.0:{port} is already in use.*"
            r"--grpc-addr or FLEET_GRPC_ADDR",
        ):
            listen_grpc("0.0.0.0", port)


def test_a_listener_that_allows_port_sharing_is_still_refused():
    """A listener with SO_REUSEPORT (as gRPC sets on its own) must not share the port with us."""
    with socket.socket() as taken:
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(ConflictError, match="already in use"):
            listen_grpc("127.0.0.1", taken.getsockname()[1])


def test_a_free_port_is_listened_on():
    sock = listen_http("127.0.0.1", 0)
    try:
        with socket.create_connection(sock.getsockname(), timeout=5):
            pass
    finally:
        sock.close()


def test_answers_on_a_kept_alive_connection_are_not_held_back_by_nagle():
    """Each connection the REST port accepts has TCP_NODELAY: without it a response's body waited
    ~40 ms for the client's delayed ACK on every request after the first of a connection."""
    listener = listen_http("127.0.0.1", 0)
    port = listener.getsockname()[1]
    accepted: list[int] = []

    async def serve_one() -> None:
        def connected(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            sock = writer.get_extra_info("socket")
            accepted.append(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
            writer.close()

        server = await asyncio.start_server(connected, sock=listener)
        async with server:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            await wait_for_async(lambda: bool(accepted), 10, "the connection to be accepted")
            writer.close()

    asyncio.run(serve_one())
    assert accepted and accepted[0] != 0


def test_the_grpc_servers_own_socket_is_private_and_fresh(tmp_path: Path):
    stale = private_socket_path(tmp_path)
    stale.write_bytes(b"left by a process that died")
    path = private_socket_path(tmp_path)
    assert path == stale and not path.exists()
    assert path.parent.stat().st_mode & 0o777 == 0o700


def test_a_data_dir_too_deep_for_a_socket_address_gets_a_private_temporary_folder(tmp_path: Path):
    deep = tmp_path / ("d" * 120)
    path = private_socket_path(deep)
    assert len(str(path)) <= 107 and not str(path).startswith(str(deep))
    assert path.parent.stat().st_mode & 0o777 == 0o700
    path.touch()
    release_private_socket(path, deep)
    assert not path.parent.exists()
    inside = private_socket_path(tmp_path)
    inside.touch()
    release_private_socket(inside, tmp_path)
    assert not inside.exists() and inside.parent.is_dir()  # the data dir's own folder stays
