"""What `fleet serve` claims before it does anything else: its data dir and its two ports.

Two processes must never share either. Two `fleet serve` on one data dir would write the same hot
runs; two on one gRPC port would split robots' streams between two depots without a word (with
SO_REUSEPORT, which gRPC sets by default, the second bind succeeds: so both ports are bound here,
without it). Each refusal is one line naming who holds what and the setting to change.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import ipaddress
import os
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

from core.errors import ConflictError

LOCK_FILE = "fleet.lock"
GRPC_SOCKET = "grpc.sock"


@contextlib.contextmanager
def hold_data_dir(
    data_dir: Path, *, what: str = "data dir", command: str = "fleet serve", fix: str = "--data-dir or FLEET_DATA_DIR"
) -> Iterator[None]:
    """An exclusive lock on the data dir for as long as the block runs (the process's life when it
    wraps `serve`). The lock file holds the owner's PID so that a refused start can name it; the
    kernel drops the lock when the process dies, however it dies, so a stale file never blocks."""
    data_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(data_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise ConflictError(
                f"the {what} is in use by another `{command}` (PID {holder}): stop that one, or give this one "
                f"its own {what} ({fix})"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _refusal(exc: OSError, host: str, port: int, what: str, setting: str) -> ConflictError:
    addr = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    if exc.errno == errno.EADDRINUSE:
        problem = "is already in use (another `fleet serve` or `fleet agent`, or another program)"
    elif exc.errno == errno.EACCES:
        problem = "needs privileges this process lacks (ports below 1024)"
    else:
        problem = f"cannot be used here ({exc.strerror or exc})"
    flag = setting.removeprefix("agent_").replace("_", "-")  # the agent's flags drop the prefix (--listen)
    return ConflictError(f"the {what} address {addr} {problem}: set another with --{flag} or FLEET_{setting.upper()}")


def split_addr(addr: str) -> tuple[str, int]:
    host, _, port = addr.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"{addr!r} is not HOST:PORT (for example 0.0.0.0:8080)")
    return host.strip("[]"), int(port)


def listen(host: str, port: int, what: str, setting: str) -> socket.socket:
    """A listening socket for one of the two ports, bound here (not by uvicorn or gRPC) so that a
    refusal is one line of ours, quick, and before anything else has changed. Made as a TCP socket
    by name: asyncio turns Nagle off (TCP_NODELAY) only on connections of such a socket, and with it
    on, each answer on a kept-alive connection waited ~40 ms for the client's delayed ACK."""
    sock = socket.socket(_family(host), socket.SOCK_STREAM, socket.IPPROTO_TCP)
    try:
        # SO_REUSEADDR (as uvicorn sets it) lets a restart bind despite TIME_WAIT connections, but
        # never while another socket listens there. No SO_REUSEPORT: a second server must fail.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        raise _refusal(exc, host, port, what, setting) from None
    sock.setblocking(False)
    return sock


def listen_http(host: str, port: int) -> socket.socket:
    """The REST API's listening socket."""
    return listen(host, port, "REST API", "http_addr")


def listen_grpc(host: str, port: int) -> socket.socket:
    """The public gRPC port's listening socket (served by `services.api.grpc_front`)."""
    return listen(host, port, "Rerun gRPC", "grpc_addr")


def private_socket_path(data_dir: Path) -> Path:
    """Where the gRPC server listens for the front of the public gRPC port: a Unix socket in a
    folder only this user can enter (so nothing reaches gRPC around the front), in the data dir
    unless that path is too long for a socket address (108 bytes on Linux)."""
    folder = data_dir.resolve() / "private"
    if len(str(folder / GRPC_SOCKET)) > 100:
        folder = Path(tempfile.mkdtemp(prefix="fleet-"))
    folder.mkdir(mode=0o700, exist_ok=True)
    folder.chmod(0o700)
    path = folder / GRPC_SOCKET
    path.unlink(missing_ok=True)  # left by a process that died; we hold the data dir
    return path


def release_private_socket(path: Path, data_dir: Path) -> None:
    """Remove the gRPC server's socket once it has stopped, and its folder if it was a temporary one."""
    path.unlink(missing_ok=True)
    if not path.parent.is_relative_to(data_dir.resolve()):
        with contextlib.suppress(OSError):
            path.parent.rmdir()


def is_loopback(host: str) -> bool:
    """Only this machine reaches `host` (127.0.0.0/8, ::1, localhost); a host name may be anywhere."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


WORKER_SOCKET = "http.sock"


def worker_socket_path(data_dir: Path) -> Path:
    """A worker's own REST socket (`fleet serve --workers N`), in its data dir's private folder."""
    return data_dir.resolve() / "private" / WORKER_SOCKET


def listen_unix(path: Path) -> socket.socket:
    """A listening Unix socket at `path` (a stale one left by a process that died is replaced), in a
    folder only this user can enter."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    path.parent.chmod(0o700)
    path.unlink(missing_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind(str(path))
    sock.listen(128)
    sock.setblocking(False)
    return sock
