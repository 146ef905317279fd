"""`MessageProxyService/WriteMessages` served on the public gRPC port by the front itself.

The front (`grpc_front`) reads each connection's first request. When it is WriteMessages (what the
Rerun SDK's GrpcSink opens first, and keeps for a whole run) the connection is served here instead
of being passed to the gRPC server: HTTP/2 frames are read straight from the socket, the gRPC
messages are cut out of DATA frames, and each stream is handed to the same handler gRPC would call
(`MessageProxy.write_messages`), through a `WriteCall` that has the few methods of a gRPC servicer
context it uses. Why: gRPC's Python server spends 50-60 us of CPU per message before the handler
sees it, more than filing a one-row chunk costs; here a message costs a few microseconds, and a
large one is read from the socket straight into its own buffer (BENCHMARKS.md, "Writes served by
the front").

What is served here is narrow on purpose: client-streaming WriteMessages, without message
compression. Any other request on such a connection is refused as HTTP/2 says a server refuses what
it did not process (GOAWAY naming the last stream it will serve, then REFUSED_STREAM): the client
sends it again on a new connection, which the front passes to the gRPC server.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import struct
from collections.abc import Callable

import grpc
from hpack import Encoder

from services.api import h2
from services.api.h2 import HeaderBlock, HeaderBlocks, ProtocolError, frame
from services.api.write_call import Aborted, BodyBudget, WriteCall, WriteHandler, grpc_message

log = logging.getLogger("fleet.grpc")

WRITE_PATH = b"/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"

# What this end announces. Large frames and windows: a 2.5 MB chunk arrives in a few frames and
# never waits for a window update; what a connection may hold unread is bounded below.
MAX_FRAME = 1 << 20
STREAM_WINDOW = 8 << 20
CONNECTION_WINDOW = 16 << 20
MAX_STREAMS = 100
MAX_HEADER_BLOCK = 1 << 20
READ_BUFFER = 1 << 20
# Messages of this size or more are read from the socket straight into a buffer of their own.
DIRECT_BYTES = 64 << 10
# Reading stops while a connection's streams hold this much that their handlers have not taken.
QUEUE_LIMIT = 32 << 20
KEEPALIVE_S = 10.0  # a silent connection is pinged after this long,
KEEPALIVE_TIMEOUT_S = 20.0  # and closed if the ping is not answered within this
_HIDDEN_METADATA = (b"te", b"content-type", b"grpc-accept-encoding")


class WriteConnection(asyncio.BufferedProtocol):
    """One client connection whose first request was WriteMessages, after the HTTP/2 preface.

    Frames are parsed from one buffer the socket is read into; while a large message's body is
    being received, the socket is read straight into that message's buffer instead (`get_buffer`)."""

    def __init__(self, handler: WriteHandler, max_message: int, on_close: Callable[[WriteConnection], None]) -> None:
        self._handler, self._on_close = handler, on_close
        self._buf = bytearray(READ_BUFFER)
        self._end = 0  # bytes in `_buf`
        self._pos = 0  # parsed up to here
        self._transport: asyncio.Transport | None = None
        self._blocks = HeaderBlocks(MAX_HEADER_BLOCK)
        self._encoder = Encoder()
        self._calls: dict[int, WriteCall] = {}
        self._tasks: dict[int, asyncio.Task[None]] = {}
        self._last_stream = 0  # the highest stream id the client opened
        self._going_away: int | None = None  # the last stream served, once GOAWAY was sent
        # the DATA frame being read: its stream (None: one no longer served), what is left of its
        # data and of its padding
        self._data_call: WriteCall | None = None
        self._data_left = 0
        self._pad_left = 0
        self._data_end_stream = False
        self._direct: memoryview | None = None  # where the socket is read into for a large body
        self._large = False  # the last message was large (or is being read straight into its buffer)
        # What is allocated ahead of a body's bytes is bounded per connection by what the client
        # may have in flight (the connection's window), not by the lengths their prefixes declare.
        self._budget = BodyBudget(CONNECTION_WINDOW, DIRECT_BYTES, max_message)
        self._credit_connection = 0  # bytes received and not yet given back as window
        self._credit: dict[int, int] = {}
        self._queued = 0  # bytes delivered to handlers and not yet taken
        self._paused = False  # reading stopped: the streams hold QUEUE_LIMIT unread
        self._write_paused = False  # reading stopped: the client does not read what this end sends
        self._last_heard = 0.0
        self._ping_sent: float | None = None
        self._keepalive: asyncio.TimerHandle | None = None
        self.closed = False

    # --- asyncio -----------------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        settings = struct.pack(
            ">HIHIHIHI",
            h2.SETTINGS_MAX_CONCURRENT_STREAMS,
            MAX_STREAMS,
            h2.SETTINGS_INITIAL_WINDOW_SIZE,
            STREAM_WINDOW,
            h2.SETTINGS_MAX_FRAME_SIZE,
            MAX_FRAME,
            h2.SETTINGS_MAX_HEADER_LIST_SIZE,
            MAX_HEADER_BLOCK,
        )
        transport.write(frame(h2.SETTINGS, 0, 0, settings) + h2.window_update(0, CONNECTION_WINDOW - 65535))
        loop = asyncio.get_running_loop()
        self._last_heard = loop.time()
        self._keepalive = loop.call_later(KEEPALIVE_S / 2, self._check_alive)

    def feed(self, data: bytes) -> None:
        """What the front read of the connection after the preface, before handing it here."""
        while data and not self.closed:
            with self.get_buffer(len(data)) as view:
                n = min(len(view), len(data))
                view[:n] = data[:n]
            self.buffer_updated(n)
            data = data[n:]

    def get_buffer(self, sizehint: int) -> memoryview:
        if self._direct is not None:
            return self._direct
        if self._pos:  # keep what is not parsed yet at the start
            rest = self._end - self._pos
            self._buf[:rest] = self._buf[self._pos : self._end]
            self._pos, self._end = 0, rest
        if len(self._buf) - self._end < max(sizehint, 65536):
            self._buf.extend(bytes(max(sizehint, len(self._buf))))
        return memoryview(self._buf)[self._end : self._end + self._read_size()]

    def _read_size(self) -> int:
        """How much to read into the buffer: all that comes, except while large messages come and
        nothing is buffered: then only the next frame's head or message's prefix, so that the body
        behind it is read straight into its own buffer (`_go_direct`), not copied there from this one."""
        if self._large and self._pos == self._end:
            if not self._data_left and not self._pad_left:
                return h2.FRAME_HEAD
            call = self._data_call
            if self._data_left and call is not None and call.body is None:
                return min(self._data_left, 5 - len(call.header))
        return len(self._buf)

    def buffer_updated(self, nbytes: int) -> None:
        self._last_heard = asyncio.get_running_loop().time()
        try:
            if self._direct is not None:
                self._direct_filled(nbytes)
            else:
                self._end += nbytes
            self._parse()
            self._give_credit()
        except ProtocolError as exc:
            self._fail_connection(exc.code, str(exc))

    def eof_received(self) -> bool:
        return False  # the transport closes; streams still open are cancelled

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        if self._keepalive is not None:
            self._keepalive.cancel()
        for task in self._tasks.values():
            task.cancel()  # a stream cut short: its handler's `finally` closes its source
        self._on_close(self)

    def close(self) -> None:
        """The front is stopping: tell the client, and end every stream (its handler cancelled
        now, not once the client has read the GOAWAY)."""
        for task in self._tasks.values():
            task.cancel()
        if self._transport is not None and not self.closed:
            self._transport.write(h2.goaway(self._last_stream, h2.NO_ERROR))
            self._transport.close()

    def abort(self) -> None:
        """Close at once, whatever is still to be sent."""
        if self._transport is not None and not self.closed:
            self._transport.abort()

    async def wait_closed(self) -> None:
        if self._tasks:
            await asyncio.gather(*self._tasks.values(), return_exceptions=True)

    # --- frames ------------------------------------------------------------------------------

    def _parse(self) -> None:
        buf = self._buf
        while True:
            if self._data_left or self._pad_left:
                if not self._data_payload():
                    return
                continue
            if self._end - self._pos < h2.FRAME_HEAD:
                return
            pos = self._pos
            length, kind, flags, stream = h2.frame_head(buf, pos)
            if length > MAX_FRAME:
                raise ProtocolError(f"a frame of {length} bytes, over {MAX_FRAME}", h2.FRAME_SIZE_ERROR)
            if kind == h2.DATA:
                if not flags & h2.PADDED and self._whole_message(pos, length, flags, stream):
                    continue
                if flags & h2.PADDED:
                    if self._end - pos < h2.FRAME_HEAD + 1:
                        return
                    pad = buf[pos + h2.FRAME_HEAD]
                    if pad >= length:
                        raise ProtocolError("DATA padding longer than the frame")
                    self._pos = pos + h2.FRAME_HEAD + 1
                    self._start_data(stream, length, length - 1 - pad, pad, flags)
                else:
                    self._pos = pos + h2.FRAME_HEAD
                    self._start_data(stream, length, length, 0, flags)
                continue
            end = pos + h2.FRAME_HEAD + length
            if self._end < end:
                return
            self._pos = end
            payload = bytes(buf[pos + h2.FRAME_HEAD : end])
            self._control(kind, flags, stream, payload)

    def _whole_message(self, pos: int, length: int, flags: int, stream: int) -> bool:
        """Take a DATA frame that is buffered whole and holds one whole small message of a stream
        between messages (what a client streaming one-row chunks sends) at once, without cutting;
        False: it is read the general way."""
        end = pos + h2.FRAME_HEAD + length
        if self._end < end or length < 5 or self._blocks.pending:
            return False
        call = self._calls.get(stream)
        if call is None or call.ended or call.dropping or call.body is not None or call.header:
            return False
        buf, at = self._buf, pos + h2.FRAME_HEAD
        size = int.from_bytes(buf[at + 1 : at + 5], "big")
        if buf[at] or size != length - 5 or size >= DIRECT_BYTES or size > self._budget.max_message:
            return False
        self._pos = end
        self._credit_connection += length
        self._credit[stream] = self._credit.get(stream, 0) + length
        call.deliver(bytes(buf[at + 5 : end]))
        if flags & h2.END_STREAM:
            call.end()
        return True

    def _start_data(self, stream: int, length: int, data: int, pad: int, flags: int) -> None:
        if self._blocks.pending:
            raise ProtocolError("a header block was interrupted by DATA")
        if stream == 0 or stream > self._last_stream:
            raise ProtocolError("DATA on a stream that was not opened")
        self._credit_connection += length
        call = self._calls.get(stream)
        if call is not None and not call.ended and not call.dropping:
            self._credit[stream] = self._credit.get(stream, 0) + length
        else:
            call = None  # ended or answered: the data is dropped (its window still counts)
        self._data_call, self._data_left, self._pad_left = call, data, pad
        self._data_end_stream = bool(flags & h2.END_STREAM)
        if not data and not pad:
            self._data_done()

    def _data_payload(self) -> bool:
        """Consume what is buffered of the DATA frame being read; False when more must be read."""
        available = self._end - self._pos
        if not available:
            call = self._data_call
            if call is not None and self._data_left and not call.dropping:
                self._go_direct(call)  # a frame's head read alone: its data can go straight in
            return False
        if self._data_left:
            take = min(available, self._data_left)
            start = self._pos
            self._pos += take
            self._data_left -= take
            call = self._data_call
            if call is not None and call.dropping:  # done with since the frame began
                self._data_call = call = None
            if call is not None:  # (None: a stream no longer served, whose data is dropped)
                with memoryview(self._buf) as whole, whole[start : start + take] as data:
                    call.cut(data)
                if call.dropping:  # it failed (a message it cannot take): the rest is dropped
                    self._data_call = None
                else:
                    self._go_direct(call)
            if self._data_left:
                return False
        take = min(self._end - self._pos, self._pad_left)
        self._pos += take
        self._pad_left -= take
        if self._pad_left:
            return False
        self._data_done()
        return True

    def _data_done(self) -> None:
        call = self._data_call
        self._data_call = None
        if call is not None and self._data_end_stream:
            call.end()

    def _go_direct(self, call: WriteCall) -> None:
        """While a large body is being received and nothing else is buffered, read the socket
        straight into it (up to the end of the DATA frame and of the body)."""
        if call.body is None or self._pos != self._end or self._pad_left or not self._data_left:
            return
        want = min(self._data_left, call.length - call.filled)
        if want >= DIRECT_BYTES // 4:
            self._direct = call.room(want).data[call.filled : call.filled + want]
            self._large = True

    def _direct_filled(self, nbytes: int) -> None:
        call = self._data_call
        assert call is not None and self._direct is not None
        self._direct.release()
        self._direct = None
        self._data_left -= nbytes
        if call.dropping:  # done with while its body was being read: the rest is dropped
            self._data_call = None
            if not self._data_left and not self._pad_left:
                self._data_done()
            return
        call.filled += nbytes
        call.complete()
        if not self._data_left and not self._pad_left:
            self._data_done()
        else:
            self._go_direct(call)

    def delivered(self, stream: int, nbytes: int) -> None:
        """A stream's handler was given a request: it holds the connection's reading back until taken."""
        self._queued += nbytes
        self._large = nbytes >= DIRECT_BYTES
        # A stream's window comes back as its handler takes what it was sent: a stream whose
        # handler is slow stops at its own window, and the connection's other streams flow.
        if stream in self._calls:
            self._credit[stream] = self._credit.get(stream, 0) - nbytes
        if self._queued > QUEUE_LIMIT and not self._paused:
            self._paused = True
            self._reading()

    def taken(self, stream: int, nbytes: int) -> None:
        """A handler took a request (or a stream ended with this much untaken)."""
        self._queued -= nbytes
        if stream in self._credit:
            self._credit[stream] += nbytes
            if self._credit[stream] >= STREAM_WINDOW // 4:
                self._give_credit()
        if self._paused and self._queued <= QUEUE_LIMIT // 2:
            self._paused = False
            self._reading()

    def _reading(self) -> None:
        """Read from the socket unless the streams hold too much or the client reads nothing."""
        if self._transport is None or self.closed:
            return
        if self._paused or self._write_paused:
            self._transport.pause_reading()
        else:
            self._transport.resume_reading()
            # what came while paused (a ping's answer among it) is read now: silence starts over
            self._last_heard, self._ping_sent = asyncio.get_running_loop().time(), None

    def pause_writing(self) -> None:
        # The client does not read: what it sends is not read either, so that answers to its
        # PINGs and SETTINGS do not pile up here.
        self._write_paused = True
        self._reading()

    def resume_writing(self) -> None:
        self._write_paused = False
        self._reading()

    def _give_credit(self) -> None:
        """Give back as window what was received, once a quarter of a window has come in."""
        out = []
        if self._credit_connection >= CONNECTION_WINDOW // 4:
            out.append(h2.window_update(0, self._credit_connection))
            self._credit_connection = 0
        for stream, credit in list(self._credit.items()):
            if credit >= STREAM_WINDOW // 4:
                out.append(h2.window_update(stream, credit))
                self._credit[stream] = 0
        if out:
            self._write(b"".join(out))

    def _control(self, kind: int, flags: int, stream: int, payload: bytes) -> None:
        if self._blocks.pending and kind != h2.CONTINUATION:
            raise ProtocolError("a header block was interrupted by another frame")
        if kind in (h2.HEADERS, h2.CONTINUATION):
            self._header_frame(kind, flags, stream, payload)
        elif kind == h2.SETTINGS:
            self._settings(flags, payload)
        elif kind == h2.PING:
            if len(payload) != 8:
                raise ProtocolError("a PING of other than 8 bytes", h2.FRAME_SIZE_ERROR)
            if flags & h2.ACK:
                self._ping_sent = None
            else:
                self._write(frame(h2.PING, h2.ACK, 0, payload))
        elif kind == h2.RST_STREAM:
            call = self._calls.get(stream)
            if call is not None:
                self._finish(call)
                call.fail(Aborted(grpc.StatusCode.CANCELLED, "the client cancelled the call"))
                if (task := self._tasks.get(stream)) is not None:
                    task.cancel()
        elif kind == h2.GOAWAY:
            self._going_away = self._going_away if self._going_away is not None else self._last_stream
        elif kind == h2.PUSH_PROMISE:
            raise ProtocolError("a client may not push")
        # WINDOW_UPDATE: what this end sends on a stream (its answer, a few hundred bytes) is far below
        # any window.
        # PRIORITY and frame types this end does not know are ignored, as HTTP/2 says.

    def _settings(self, flags: int, payload: bytes) -> None:
        if flags & h2.ACK:
            return
        if len(payload) % 6:
            raise ProtocolError("SETTINGS of a length not a multiple of 6", h2.FRAME_SIZE_ERROR)
        for key, value in struct.iter_unpack(">HI", payload):
            if key == h2.SETTINGS_HEADER_TABLE_SIZE:  # what this end's encoder may use
                self._encoder.header_table_size = min(value, 4096)
            elif key == h2.SETTINGS_INITIAL_WINDOW_SIZE and value > 0x7FFFFFFF:
                raise ProtocolError("an initial window over 2^31-1", h2.FLOW_CONTROL_ERROR)
        self._write(frame(h2.SETTINGS, h2.ACK, 0))

    def _header_frame(self, kind: int, flags: int, stream: int, payload: bytes) -> None:
        block = self._blocks.add(kind, flags, stream, payload)
        if block is None:
            return
        if stream in self._calls:  # trailers from the client: only their end counts
            if block.flags & h2.END_STREAM:
                self._calls[stream].end()
            return
        if stream <= self._last_stream:
            return  # the end of a stream already answered or refused
        self._open(block)

    def _open(self, block: HeaderBlock) -> None:
        stream, headers = block.stream, block.headers
        if stream % 2 == 0 or stream <= self._last_stream:
            raise ProtocolError(f"stream {stream} opened out of order")
        self._last_stream = stream
        path = next((value for name, value in headers if name == b":path"), b"")
        if self._going_away is not None or path != WRITE_PATH:
            self._refuse(stream, path)
            return
        if len(self._calls) >= MAX_STREAMS:
            self._write(h2.rst_stream(stream, h2.REFUSED_STREAM))
            return
        metadata = tuple(
            (name.decode("latin-1"), h2.binary_value(value) if name.endswith(b"-bin") else value.decode("latin-1"))
            for name, value in headers
            if not name.startswith(b":") and name not in _HIDDEN_METADATA
        )
        call = self._calls[stream] = WriteCall(stream, metadata, self, self._budget)
        if block.flags & h2.END_STREAM:
            call.end()
        task = self._tasks[stream] = asyncio.get_running_loop().create_task(self._serve(call))
        task.add_done_callback(lambda _: self._tasks.pop(stream, None))

    def _refuse(self, stream: int, path: bytes) -> None:
        """A request other than WriteMessages: the client is to send it on a new connection."""
        if self._going_away is None:
            self._going_away = stream - 2 if stream > 1 else 0
            log.debug("gRPC port: %r on a write connection: the client is sent to a new connection", path)
            self._write(h2.goaway(self._going_away, h2.NO_ERROR))
        self._write(h2.rst_stream(stream, h2.REFUSED_STREAM))
        self._close_if_done()

    async def _serve(self, call: WriteCall) -> None:
        status, details, body = grpc.StatusCode.OK, "", None
        try:
            response = await self._handler(call.requests(), call)
            body = response.SerializeToString() if hasattr(response, "SerializeToString") else bytes(response)
        except Aborted as exc:
            status, details = exc.code, exc.details
        except asyncio.CancelledError:
            self._finish(call)
            return  # the client went away or cancelled: nobody to answer
        except Exception:
            log.exception("WriteMessages failed")
            status, details = grpc.StatusCode.INTERNAL, "the depot failed on this stream; see its log"
        self._answer(call, status, details, body)

    def _finish(self, call: WriteCall) -> bool:
        """The stream is done with (answered, reset or cut short): what more the client sends on it
        is dropped, and what its handler left unread no longer holds the connection's reading back.
        False if it was done with already."""
        if self._calls.pop(call.stream_id, None) is None:
            return False
        self._credit.pop(call.stream_id, None)
        self.taken(call.stream_id, call.discard())
        return True

    def _answer(self, call: WriteCall, status: grpc.StatusCode, details: str, body: bytes | None) -> None:
        if not self._finish(call) or self.closed:
            return
        stream = call.stream_id
        trailers = [(b"grpc-status", str(status.value[0]).encode())]
        if details:
            trailers.append((b"grpc-message", grpc_message(details).encode()))
        trailers += [(k.encode(), h2.metadata_value(k, v)) for k, v in call.trailing]
        head = [(b":status", b"200"), (b"content-type", b"application/grpc")]
        # Frames of at most 16 KiB (what every client accepts). The answer is an empty
        # WriteMessagesResponse and a status: far below any flow-control window.
        if body is None:  # trailers only
            out = h2.header_frames(stream, self._encoder.encode(head + trailers), h2.END_STREAM)
        else:
            out = (
                h2.header_frames(stream, self._encoder.encode(head), 0)
                + h2.data_frames(stream, b"\0" + len(body).to_bytes(4, "big") + body)
                + h2.header_frames(stream, self._encoder.encode(trailers), h2.END_STREAM)
            )
        if not call.ended:  # answered before the client finished: it is to stop sending
            out += h2.rst_stream(stream, h2.NO_ERROR)
        self._write(out)
        self._close_if_done()

    def _close_if_done(self) -> None:
        if self._going_away is not None and not self._calls and self._transport is not None:
            self._transport.close()

    def _write(self, data: bytes) -> None:
        if self._transport is not None and not self.closed:
            self._transport.write(data)

    def _fail_connection(self, code: int, reason: str) -> None:
        log.info("gRPC port: connection closed: %s", reason)
        for call in self._calls.values():
            call.fail(Aborted(grpc.StatusCode.INTERNAL, f"the connection broke HTTP/2: {reason}"))
        if self._transport is not None and not self.closed:
            self._transport.write(h2.goaway(self._last_stream, code, reason.encode()[:200]))
            self._transport.close()
        self.closed = True

    def _check_alive(self) -> None:
        """Keepalive: ping a connection that went silent; close one that does not answer."""
        if self.closed or self._transport is None:
            return
        loop = asyncio.get_running_loop()
        now = loop.time()
        # While reading is paused for its handlers' sake, the answer waits unread in the socket.
        if self._ping_sent is not None and now - self._ping_sent > KEEPALIVE_TIMEOUT_S and not self._paused:
            log.info("gRPC port: a write connection did not answer a ping for %g s: closed", KEEPALIVE_TIMEOUT_S)
            self._transport.abort()
            return
        if self._ping_sent is None and now - self._last_heard > KEEPALIVE_S:
            self._ping_sent = now
            self._write(frame(h2.PING, 0, 0, b"fleet-ka"))
        self._keepalive = loop.call_later(KEEPALIVE_S / 2, self._check_alive)


class WriteServer:
    """The write connections the front has handed over, and the handler their streams go to."""

    def __init__(self, handler: WriteHandler, max_message: int) -> None:
        self.handler, self.max_message = handler, max_message
        self.connections: set[WriteConnection] = set()
        self.stopped = False

    async def take(self, sock: socket.socket, held: bytes) -> None:
        """Serve a client connection here from now on; `held`: what was read of it after the
        preface (its first request's headers among it)."""
        if self.stopped:  # handed over as the node stops: the client connects again elsewhere
            sock.close()
            return
        connection = WriteConnection(self.handler, self.max_message, self.connections.discard)
        self.connections.add(connection)
        await asyncio.get_running_loop().connect_accepted_socket(lambda: connection, sock=sock)
        connection.feed(held)

    async def stop(self) -> None:
        """Tell every client this node is going away and end its streams (their sources closed)."""
        connections = list(self.connections)
        self.stopped = True
        for connection in connections:
            connection.close()
        await asyncio.gather(*(c.wait_closed() for c in connections), return_exceptions=True)
        for connection in connections:
            connection.abort()  # a client that reads nothing would hold its connection open
