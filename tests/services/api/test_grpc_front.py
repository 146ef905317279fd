"""The public gRPC port's front: what passes untouched, what is rewritten, and what it answers itself."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import h2.config
import h2.connection
import h2.events
import httpx
import pytest
from hpack import Decoder, Encoder

from services import __version__
from services.api.grpc_front import ClientStream, http1_answer
from services.api.h2 import PREFACE, ProtocolError
from services.api.h2 import frame as _frame
from services.ingest.grpc_handler import LEGACY_REFUSAL
from tests.services.ingest.live_server import LiveServer

SETTINGS = _frame(0x4, 0, 0, b"")
DATA = _frame(0x0, 0x1, 1, b"\x00\x00\x00\x00\x02hi")


LEGACY_WRITE = b"/rerun.sdk_comms.v0.MessageProxy/WriteMessages"


def request_headers(scheme: bytes, path: bytes = LEGACY_WRITE) -> list[tuple[bytes, bytes]]:
    return [
        (b":method", b"POST"),
        (b":scheme", scheme),
        (b":path", path),
        (b":authority", b"depot:51234"),
        (b"content-type", b"application/grpc"),
        (b"te", b"trailers"),
        (b"user-agent", b"rerun-sdk/0.22"),
    ]


def frames(data: bytes) -> list[tuple[int, int, int, bytes]]:
    out, pos = [], 0
    while pos < len(data):
        length = int.from_bytes(data[pos : pos + 3], "big")
        out.append(
            (
                data[pos + 3],
                data[pos + 4],
                int.from_bytes(data[pos + 5 : pos + 9], "big"),
                data[pos + 9 : pos + 9 + length],
            )
        )
        pos += 9 + length
    assert pos == len(data)
    return out


def header_blocks(data: bytes) -> list[list[tuple[bytes, bytes]]]:
    """What a server decodes from the front's output: every header block, in order."""
    decoder, blocks, block = Decoder(), [], b""
    for kind, flags, _, payload in frames(data):
        if kind == 0x1:
            block = payload[5:] if flags & 0x20 else payload
        elif kind == 0x9:
            block += payload
        if kind in (0x1, 0x9) and flags & 0x4:
            blocks.append([(bytes(n), bytes(v)) for n, v in decoder.decode(block, raw=True)])
    return blocks


def feed_all(stream: ClientStream, data: bytes, step: int) -> bytes | None:
    out = b""
    for i in range(0, len(data), step):
        part = stream.feed(data[i : i + step])
        if part is None:
            return None
        out += part
    return out


@pytest.mark.parametrize("step", [1, 7, 10_000])
def test_plain_schemes_pass_untouched(step: int):
    encoder = Encoder()
    data = SETTINGS + _frame(0x1, 0x4, 1, encoder.encode(request_headers(b"http"))) + DATA
    stream = ClientStream()
    assert feed_all(stream, data, step) is None and stream.passthrough


@pytest.mark.parametrize("step", [1, 5, 10_000])
def test_rerun_schemes_are_rewritten_in_every_request_and_nothing_else_changes(step: int):
    encoder = Encoder()  # one client table across requests, as a real client compresses
    first = encoder.encode(request_headers(b"rerun+http"))
    second = encoder.encode(request_headers(b"rerun+https", b"/other/Call"))
    padded = bytes([3]) + b"\x80\x00\x00\x00\x10" + second + b"\x00\x00\x00"  # pad length, priority, pad
    data = (
        SETTINGS
        + _frame(0x1, 0x0, 1, first[:4])
        + _frame(0x9, 0x4, 1, first[4:])
        + DATA
        + _frame(0x1, 0x4 | 0x8 | 0x20 | 0x1, 3, padded)
    )
    out = feed_all(ClientStream(), data, step)
    assert out is not None
    assert out.startswith(SETTINGS) and DATA in out
    first_block, second_block = header_blocks(out)
    assert first_block == request_headers(b"http")
    assert second_block == request_headers(b"https", b"/other/Call")
    last = frames(out)[-1]
    assert last[0] == 0x1 and last[1] & 0x1 and last[1] & 0x20 and last[2] == 3  # END_STREAM, PRIORITY kept
    assert last[3][:5] == b"\x80\x00\x00\x00\x10"


def test_a_header_block_bigger_than_a_frame_is_split_into_continuations():
    big = [*request_headers(b"rerun+http"), (b"x-big", b"v" * 40_000)]
    data = SETTINGS + b"".join(
        _frame(0x9 if i else 0x1, 0x4 if i + 16_000 >= len(e) else 0, 1, e[i : i + 16_000])
        for e in [Encoder().encode(big, huffman=False)]
        for i in range(0, len(e), 16_000)
    )
    out = ClientStream().feed(data)
    assert out is not None
    assert all(len(payload) <= 16384 for _, _, _, payload in frames(out))
    assert header_blocks(out) == [[*request_headers(b"http"), (b"x-big", b"v" * 40_000)]]


@pytest.mark.parametrize(
    "data, problem",
    [
        (_frame(0x9, 0x4, 1, b"\x82"), "CONTINUATION without its HEADERS"),
        (_frame(0x1, 0x0, 1, b"\x82") + DATA, "interrupted"),
        (_frame(0x1, 0x4, 1, b"\xff\xff\xff\xff\xff"), "undecodable"),
        (_frame(0x1, 0x4 | 0x8, 1, b"\x09\x82"), "padding"),
    ],
)
def test_broken_http2_is_refused(data: bytes, problem: str):
    with pytest.raises(ProtocolError, match=problem):
        ClientStream().feed(SETTINGS + data)


def test_http1_gets_the_version_and_nothing_else():
    answer = http1_answer(b"GET /version HTTP/1.1\r\nhost: depot\r\n\r\n", "fleet-telemetry 1.2.3")
    assert answer.startswith(b"HTTP/1.1 200 OK\r\n") and answer.endswith(b"\r\n\r\nfleet-telemetry 1.2.3\n")
    head = http1_answer(b"HEAD /version HTTP/1.1\r\n\r\n", "v")
    assert head.endswith(b"content-length: 2\r\nconnection: close\r\n\r\n")
    other = http1_answer(b"GET /v1/runs HTTP/1.1\r\n\r\n", "v")
    assert other.startswith(b"HTTP/1.1 404 ") and b"REST API is on the depot's HTTP port" in other


# --- through a live `fleet serve` -----------------------------------------------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    live = LiveServer(tmp_path_factory.mktemp("front") / "data").start()
    try:
        yield live
    finally:
        live.stop()


@pytest.mark.slow  # starts fleet serve
def test_get_version_on_the_grpc_port(server: LiveServer):
    answer = httpx.get(f"http://127.0.0.1:{server.grpc_port}/version", timeout=10)
    assert answer.status_code == 200 and answer.text == f"fleet-telemetry {__version__}\n"


def grpc_call_over_h2(port: int, scheme: str, calls: int) -> list[dict[str, str]]:
    """`calls` gRPC calls, one after another on one HTTP/2 connection, each an empty message to
    0.22's WriteMessages, sent with the given `:scheme`: the trailers of each answer."""
    conn = h2.connection.H2Connection(h2.config.H2Configuration(client_side=True, header_encoding="utf-8"))
    conn.initiate_connection()
    answers: list[dict[str, str]] = []
    with socket.create_connection(("127.0.0.1", port), timeout=20) as sock:
        sock.sendall(conn.data_to_send())
        for _ in range(calls):
            stream = conn.get_next_available_stream_id()
            conn.send_headers(stream, [(k.decode(), v.decode()) for k, v in request_headers(scheme.encode())])
            conn.send_data(stream, b"\x00\x00\x00\x00\x00", end_stream=True)
            sock.sendall(conn.data_to_send())
            trailers: dict[str, str] | None = None
            while trailers is None:
                data = sock.recv(65536)
                assert data, "the depot closed the connection"
                for event in conn.receive_data(data):
                    if isinstance(event, h2.events.StreamReset):
                        raise AssertionError(f"stream reset with error {event.error_code}")
                    if isinstance(event, (h2.events.TrailersReceived, h2.events.ResponseReceived)):
                        headers = {str(k): str(v) for k, v in event.headers or ()}
                        trailers = headers if "grpc-status" in headers else None
                    if isinstance(event, h2.events.DataReceived):
                        conn.acknowledge_received_data(event.flow_controlled_length, event.stream_id)
                sock.sendall(conn.data_to_send())
            answers.append(trailers)
    return answers


@pytest.mark.slow  # starts fleet serve
@pytest.mark.parametrize("scheme", ["rerun+http", "http"])
def test_requests_reach_the_depot_whatever_their_scheme(server: LiveServer, scheme: str):
    """rerun-sdk 0.22 sends `:scheme: rerun+http`, which gRPC alone refuses before the depot can
    answer; through the front every request of such a connection gets the depot's answer."""
    for trailers in grpc_call_over_h2(server.grpc_port, scheme, calls=3):
        assert trailers["grpc-status"] == "9"  # FAILED_PRECONDITION: the depot's handler answered
        assert trailers["grpc-message"] == LEGACY_REFUSAL


@pytest.mark.slow  # starts fleet serve
def test_garbage_on_the_grpc_port_is_closed_and_the_port_keeps_serving(server: LiveServer):
    with socket.create_connection(("127.0.0.1", server.grpc_port), timeout=20) as sock:
        sock.sendall(b"\x16\x03\x01" + b"\x00" * 20_000)  # say, TLS to a plain port
        assert sock.recv(100) == b""
    with socket.create_connection(("127.0.0.1", server.grpc_port), timeout=20) as sock:
        sock.sendall(PREFACE + _frame(0x9, 0x4, 1, b"\x82"))
        answer = _read_to_end(sock)  # the server's opening SETTINGS, then the close
        assert answer[3] == 0x4 and len(answer) == 9 + int.from_bytes(answer[:3], "big")
    assert httpx.get(f"http://127.0.0.1:{server.grpc_port}/version", timeout=10).status_code == 200
    assert server.write_messages([])[0].name == "OK"


@pytest.mark.slow  # starts fleet serve
def test_the_grpc_server_is_not_reachable_around_the_front(server: LiveServer):
    path = Path(server.data_dir) / "private" / "grpc.sock"
    assert path.exists() and path.parent.stat().st_mode & 0o077 == 0


def open_fds(server: LiveServer) -> int:
    assert server.proc is not None
    return len(list(Path(f"/proc/{server.proc.pid}/fd").iterdir()))


@pytest.mark.slow  # starts fleet serve
def test_connections_leave_no_descriptors_behind(server: LiveServer):
    """Every way a connection ends (a finished call, a client that vanishes mid-stream, a request
    for /version, a rewritten connection) closes both of its sockets and its pipes."""
    assert server.write_messages([])[0].name == "OK"  # gRPC's own lazily opened descriptors
    before = open_fds(server)
    for _ in range(20):
        assert server.write_messages([])[0].name == "OK"
        grpc_call_over_h2(server.grpc_port, "rerun+http", calls=1)
        assert httpx.get(f"http://127.0.0.1:{server.grpc_port}/version", timeout=10).status_code == 200
        with socket.create_connection(("127.0.0.1", server.grpc_port), timeout=20) as sock:
            sock.sendall(PREFACE + SETTINGS)  # then gone, in the middle of the connection
    server.wait_for(lambda: open_fds(server) <= before + 2, timeout=30, what="descriptors to be closed")


def _read_to_end(sock: socket.socket) -> bytes:
    data = b""
    while more := sock.recv(65536):
        data += more
    return data
