"""Mutated real recordings: the decoder and chunk reader raise only `RrdError`, never crash or hang.

One small recording is written by the real rerun-sdk (in a subprocess), then hypothesis flips
bytes, truncates, inserts, deletes and duplicates byte runs and overwrites message headers. Each
mutated input is decoded with `RrdDecoder`, fed in random-size pieces, and `chunk_meta` is run on
every Arrow message, then the full validation ingest applies (`check_chunk`, `validated_batch`);
a chunk that passes it has every value read (`to_pylist`), which must never crash.

The decoding runs in a long-lived worker subprocess, so that a crash in native code (pyarrow,
lz4, protobuf) fails the one example instead of killing pytest, and a hang is cut after
`EXAMPLE_SECONDS`. The worker answers with the events (offset, type, end), the error and the
outcome of each `chunk_meta`.
"""

from __future__ import annotations

import json
import os
import select
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lz4.block
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from services.rrd import errors
from services.rrd.chunk import chunk_meta, decompress_payload
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE, RrdDecoder
from services.rrd.messages import ArrowMessage, StreamFooter, StreamStart
from services.rrd.pb import log_msg_pb2

pytestmark = [pytest.mark.sdk]

REPO_ROOT = Path(__file__).resolve().parents[3]
EXAMPLE_SECONDS = 5.0
MAX_WORKER_RSS_MIB = 1024

FUZZ = settings(
    max_examples=200,
    deadline=None,
    derandomize=True,  # the same examples on every run, so CI is reproducible
    database=None,
    # No shrinking: a native crash restarts the worker for every shrink step. The mutations are
    # small descriptions already (a few positions and values), printed as they were drawn.
    phases=[Phase.explicit, Phase.generate],
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

SDK_SCRIPT = """
import sys
import rerun as rr

rec = rr.RecordingStream("fuzz", recording_id="fuzz-1")
rec.save(sys.argv[1])
rec.send_property("fleet", rr.AnyValues(robot_id="robot-1", tags=["a", "bb", "ccc"], api_token="s3cret"))
for frame in range(3):
    rec.set_time("frame", sequence=frame)
    rec.log("world/points", rr.Points3D([[frame, 0, 0], [0, frame, 1], [1, 1, frame]]))
    rec.log("robot/speed", rr.Scalars([frame * 0.5, frame]))
    rec.log("log", rr.TextLog(f"step {frame}", level="INFO"))
    rec.log("tf", rr.Transform3D(translation=[frame, 0, 0], quaternion=[0, 0, 0, 1]))
rec.flush()
"""

WORKER_SCRIPT = r"""
import json, struct, sys, time, traceback

import pyarrow as pa

from services.rrd.chunk import chunk_meta, decompress_payload
from services.rrd.decoder import RrdDecoder
from services.rrd.errors import RrdError
from services.rrd.messages import ArrowMessage, StreamFooter, StreamStart
from services.rrd.validate import check_chunk, validated_batch


def end_of(event):
    if isinstance(event, StreamStart):
        return event.offset + 12
    if isinstance(event, StreamFooter):  # reported once the whole 32-byte trailer is read
        return event.offset + 32
    return event.offset + 16 + len(event.raw)


def describe(exc):
    info = {"type": type(exc).__name__, "rrd": isinstance(exc, RrdError), "text": str(exc)}
    if isinstance(exc, RrdError):
        info["offset"] = exc.offset
    else:
        info["traceback"] = traceback.format_exc()
    return info


def peak_rss_kib():
    # VmHWM is this process's own peak; getrusage's ru_maxrss keeps the peak of the process that
    # forked it (Linux carries it across exec), so a large test runner would be counted.
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:"))


def read_every_value(batch):
    # Validated: every value can be read (timelines as int64: datetime cannot hold nanoseconds).
    for column in batch.columns:
        if pa.types.is_temporal(column.type):
            column = column.view(pa.int64())
        column.to_pylist()


def run(data, pieces):
    started = time.monotonic()
    events, error, chunks = [], None, []
    decoder = RrdDecoder()
    try:
        pos = 0
        for size in pieces:
            events += decoder.feed(data[pos:pos + size])
            pos += size
        events += decoder.feed(data[pos:])
        events += decoder.finish()
    except Exception as exc:
        error = describe(exc)
    for event in events:
        if isinstance(event, ArrowMessage):
            try:
                meta = chunk_meta(event)
                check_chunk(event, meta)
                read_every_value(validated_batch(event, meta))
                chunks.append(None)
            except Exception as exc:
                chunks.append(describe(exc))
    return {
        "events": [[e.offset, type(e).__name__, end_of(e)] for e in events],
        "error": error,
        "chunks": chunks,
        "seconds": time.monotonic() - started,
        "maxrss_kib": peak_rss_kib(),
    }


stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
stdout.write(b"ready\n")
stdout.flush()
while True:
    head = stdin.read(8)
    if len(head) < 8:
        break
    data_len, n_pieces = struct.unpack("<II", head)
    pieces = struct.unpack(f"<{n_pieces}I", stdin.read(4 * n_pieces))
    data = stdin.read(data_len)
    blob = json.dumps(run(data, pieces)).encode()
    stdout.write(struct.pack("<I", len(blob)) + blob)
    stdout.flush()
"""


class WorkerFailure(AssertionError):
    pass


class Worker:
    """A subprocess running WORKER_SCRIPT; restarted after it crashes or hangs."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None
        self.stderr = tempfile.TemporaryFile()  # noqa: SIM115 (lives as long as the worker)

    def _start(self) -> subprocess.Popen[bytes]:
        self.stderr.seek(0)
        self.stderr.truncate()
        proc = subprocess.Popen(
            [sys.executable, "-X", "faulthandler", "-c", WORKER_SCRIPT],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self.stderr,
            cwd=REPO_ROOT,
        )
        self.proc = proc
        line = self._read(6, time.monotonic() + 60)
        assert line == b"ready\n", line
        return proc

    def _read(self, n: int, deadline: float) -> bytes:
        assert self.proc is not None and self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        out = bytearray()
        while len(out) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([fd], [], [], remaining)[0]:
                raise TimeoutError
            chunk = os.read(fd, n - len(out))
            if not chunk:
                raise EOFError
            out += chunk
        return bytes(out)

    def _stop(self) -> str:
        """Kill the worker (it hung or crashed) and return the end of its stderr."""
        proc, self.proc = self.proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=30)
        self.stderr.seek(0)
        return self.stderr.read().decode(errors="replace")[-4000:]

    def run(self, data: bytes, pieces: list[int]) -> dict[str, Any]:
        proc = self.proc if self.proc is not None and self.proc.poll() is None else self._start()
        assert proc.stdin is not None
        started = time.monotonic()
        deadline = started + EXAMPLE_SECONDS
        try:
            proc.stdin.write(struct.pack("<II", len(data), len(pieces)))
            proc.stdin.write(struct.pack(f"<{len(pieces)}I", *pieces) + data)
            proc.stdin.flush()
            (size,) = struct.unpack("<I", self._read(4, deadline))
            result: dict[str, Any] = json.loads(self._read(size, deadline + 5))
        except TimeoutError:
            stderr = self._stop()
            raise WorkerFailure(f"decoding did not finish within {EXAMPLE_SECONDS} s (hang?)\n{stderr}") from None
        except (EOFError, BrokenPipeError):
            code = proc.wait(timeout=30)
            stderr = self._stop()
            raise WorkerFailure(f"the decoding process crashed (exit status {code})\n{stderr}") from None
        result["wall_seconds"] = time.monotonic() - started
        return result

    def close(self) -> None:
        if self.proc is not None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._stop()
        self.stderr.close()


class Recording:
    """The intact recording and what it decodes to (not a dataclass: hypothesis prints it)."""

    def __init__(
        self,
        data: bytes,
        events: list[tuple[int, str, int]],
        message_headers: list[int],
        chunks: list[tuple[int, bytes]],
    ) -> None:
        self.data = data
        self.events = events  # (offset, type name, end) of each event of the intact file
        self.message_headers = message_headers  # offsets of the 16-byte message headers
        self.chunks = chunks  # (offset, Arrow IPC bytes) of each Arrow message

    def __repr__(self) -> str:
        return f"<Recording of {len(self.data)} bytes: {self.events}>"

    def stable_events(self, first_change: int) -> list[tuple[int, str, int]]:
        """The intact events that end before `first_change`: any mutation there leaves them be."""
        return [e for e in self.events if e[2] <= first_change]


def _end_of(event: Any) -> int:
    if isinstance(event, StreamStart):
        return int(event.offset) + 12
    if isinstance(event, StreamFooter):  # reported once the whole 32-byte trailer is read
        return int(event.offset) + 32
    return int(event.offset) + 16 + len(event.raw)


def _summary(events: list[Any]) -> list[tuple[int, str, int]]:
    return [(int(e.offset), type(e).__name__, _end_of(e)) for e in events]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    path = tmp_path_factory.mktemp("fuzz") / "fuzz.rrd"
    done = subprocess.run([sys.executable, "-c", SDK_SCRIPT, str(path)], capture_output=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    data = path.read_bytes()
    decoder = RrdDecoder()
    events = decoder.feed(data) + decoder.finish()
    headers = [e.offset for e in events if not isinstance(e, (StreamStart, StreamFooter))]
    chunks = [(e.offset, decompress_payload(e)) for e in events if isinstance(e, ArrowMessage)]
    return Recording(data, _summary(events), headers, chunks)


@pytest.fixture(scope="module")
def worker() -> Iterator[Worker]:
    w = Worker()
    try:
        yield w
    finally:
        w.close()


def first_difference(a: bytes, b: bytes) -> int:
    n = min(len(a), len(b))
    if a[:n] == b[:n]:
        return n
    lo, hi = 0, n  # the first differing index is in [lo, hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if a[lo:mid] == b[lo:mid]:
            lo = mid
        else:
            hi = mid
    return lo


def _unexpected(what: str, info: dict[str, Any]) -> str:
    return f"{what} raised {info['type']} (not an RrdError): {info['text']}\n{info.get('traceback', '')}"


def check(worker: Worker, recording: Recording, data: bytes, pieces: list[int]) -> dict[str, Any]:
    """Decode `data` in the worker and check the contract; return the worker's result."""
    result = worker.run(data, pieces)
    error = result["error"]
    if error is not None:
        assert error["rrd"], _unexpected("RrdDecoder", error)
        assert 0 <= error["offset"] <= len(data), error
        assert f"at byte {error['offset']}" in error["text"], error
    for info in result["chunks"]:
        if info is not None:
            assert info["rrd"], _unexpected("chunk_meta", info)
            assert 0 <= info["offset"] < len(data), info
            assert info["type"] in (
                "DecompressionError",
                "NotAChunkError",
                "InvalidChunkError",
                "MessageTooLargeError",
            ), info
    assert result["seconds"] < EXAMPLE_SECONDS and result["wall_seconds"] < EXAMPLE_SECONDS
    assert result["maxrss_kib"] < MAX_WORKER_RSS_MIB * 1024, f"worker RSS {result['maxrss_kib']} KiB"
    # What came before the first changed byte decodes as in the intact file.
    stable = recording.stable_events(first_difference(recording.data, data))
    got = [tuple(e) for e in result["events"]]
    n = min(len(got), len(stable))
    assert got[:n] == stable[:n]
    return result


def pieces_strategy() -> st.SearchStrategy[list[int]]:
    # Many pieces: events returned by the feeds before a fault are checked (and chunk_meta'd).
    return st.lists(st.integers(1, 2048), max_size=16)


def position(data: st.DataObject, recording: Recording) -> int:
    """A byte position, half the time inside one message (most of the file is the footer)."""
    spans = [(start, end) for start, _, end in recording.events]
    start, end = data.draw(st.one_of(st.just((0, len(recording.data))), st.sampled_from(spans)), label="span")
    return int(data.draw(st.integers(start, end - 1), label="position"))


def _message_raw(recording: Recording, offset: int) -> bytes:
    (length,) = struct.unpack_from("<Q", recording.data, offset + 8)
    return recording.data[offset + 16 : offset + 16 + length]


# --- the intact recording ------------------------------------------------------------------


def test_recording_decodes(recording: Recording, worker: Worker) -> None:
    kinds = [kind for _, kind, _ in recording.events]
    assert kinds[0] == "StreamStart" and kinds[-2:] == ["EndMessage", "StreamFooter"]
    assert kinds.count("ArrowMessage") >= 4  # properties, points, scalars, text log
    assert recording.events[-1][2] == len(recording.data)
    decoder = RrdDecoder()
    entities = {chunk_meta(e).entity_path for e in decoder.feed(recording.data) if isinstance(e, ArrowMessage)}
    assert {"/world/points", "/robot/speed", "/log", "/tf", "/__properties/fleet"} <= entities
    result = check(worker, recording, recording.data, [1, 2, 3, 100])
    assert result["error"] is None and result["chunks"] == [None] * kinds.count("ArrowMessage")
    assert [tuple(e) for e in result["events"]] == recording.events


def test_recording_concatenated_with_itself(recording: Recording) -> None:
    decoder = RrdDecoder()
    events = decoder.feed(recording.data + recording.data) + decoder.finish()
    n = len(recording.data)
    shifted = [(offset + n, kind, end + n) for offset, kind, end in recording.events]
    assert _summary(events) == recording.events + shifted


# --- truncation at every offset ------------------------------------------------------------


@pytest.mark.timeout(120)
def test_truncation_at_every_offset(recording: Recording) -> None:
    """A cut at a message boundary decodes; any other cut raises TruncatedError from finish(),
    after returning exactly the events that end before the cut."""
    data = recording.data
    boundaries = {end for _, kind, end in recording.events if kind != "StreamFooter"} | {len(data)}
    started = time.monotonic()
    wrong: list[str] = []
    for cut in range(len(data) + 1):
        expected = recording.stable_events(cut)
        last_end = expected[-1][2] if expected else 0
        # A cut stream trailer may also be reported where it starts.
        trailer = expected[-1][0] if expected and expected[-1][1] == "StreamFooter" else None
        for split in (cut, cut // 2):  # one piece, and two pieces
            decoder = RrdDecoder()
            events = decoder.feed(data[:split]) + decoder.feed(data[split:cut])
            assert _summary(events) == expected, f"cut at {cut}"
            try:
                events += decoder.finish()
            except errors.RrdError as exc:
                if cut == 0:
                    assert type(exc) is errors.NotAnRrdError
                elif type(exc) is not errors.TruncatedError or cut in boundaries:
                    wrong.append(f"cut at {cut} (split {split}): {type(exc).__name__}: {exc}")
                else:  # the torn unit starts where the last complete one ends
                    assert exc.offset in (last_end, trailer), f"cut at {cut}: {exc}"
                    assert f"at byte {exc.offset}" in str(exc)
            else:
                if cut not in boundaries:
                    wrong.append(f"cut at {cut} (split {split}): not a message boundary, decoded without error")
                assert _summary(events) == expected
    assert not wrong, "\n".join(wrong[:20])
    assert time.monotonic() - started < 60


# --- hypothesis: mutations ------------------------------------------------------------------


@pytest.mark.timeout(120)
@FUZZ
@given(data=st.data())
def test_flipped_bytes(recording: Recording, worker: Worker, data: st.DataObject) -> None:
    mutated = bytearray(recording.data)
    for _ in range(data.draw(st.integers(1, 4), label="flips")):
        pos = position(data, recording)
        mutated[pos] ^= data.draw(st.integers(1, 255), label="xor")
    check(worker, recording, bytes(mutated), data.draw(pieces_strategy(), label="pieces"))


@pytest.mark.timeout(120)
@FUZZ
@given(data=st.data())
def test_flipped_bytes_in_arrow_ipc(recording: Recording, worker: Worker, data: st.DataObject) -> None:
    """Damage inside one chunk's Arrow IPC bytes (re-compressed, so LZ4 stays valid): the stream
    decodes, and chunk_meta must report NotAChunkError or succeed, never crash.

    Besides byte flips, an int64 found at some position is replaced everywhere it occurs, which
    changes a length consistently (record batch and field nodes) while the buffers stay small."""
    offset, ipc = recording.chunks[data.draw(st.integers(0, len(recording.chunks) - 1), label="chunk")]
    mutated = bytearray(ipc)
    # 8-aligned int64s holding small positive values: lengths, counts, buffer offsets and sizes.
    small_ints = [i for i in range(0, len(ipc) - 7, 8) if 0 < struct.unpack_from("<q", ipc, i)[0] <= 4096]
    for _ in range(data.draw(st.integers(1, 4), label="edits")):
        if data.draw(st.booleans(), label="replace int64 everywhere"):
            pos = data.draw(st.sampled_from(small_ints), label="position")
            old = bytes(mutated[pos : pos + 8])
            new = struct.pack(
                "<q",
                data.draw(
                    st.one_of(st.integers(-(2**63), 2**63 - 1), st.sampled_from([0, -1, 1 << 31, 1 << 40])),
                    label="int64",
                ),
            )
            mutated = bytearray(bytes(mutated).replace(old, new))
        else:
            pos = data.draw(st.integers(0, len(mutated) - 1), label="position")
            mutated[pos] ^= data.draw(st.integers(1, 255), label="xor")
    pb = log_msg_pb2.ArrowMsg.FromString(_message_raw(recording, offset))
    if data.draw(st.booleans(), label="lz4"):
        pb.payload = lz4.block.compress(bytes(mutated), store_size=False)
    else:
        pb.compression = 1  # type: ignore[assignment]  # Compression.NONE
        pb.payload = bytes(mutated)
    pb.uncompressed_size = len(mutated)
    raw = pb.SerializeToString()
    # The stream up to this chunk, then the damaged chunk; no End (a footer-less file).
    stream = recording.data[:offset] + struct.pack("<QQ", 2, len(raw)) + raw
    result = check(worker, recording, stream, data.draw(pieces_strategy(), label="pieces"))
    assert result["error"] is None, result["error"]
    assert result["events"][-1][:2] == [offset, "ArrowMessage"]


@pytest.mark.timeout(120)
@FUZZ
@given(cut=st.integers(0, 1 << 20), pieces=pieces_strategy())
def test_truncated(recording: Recording, worker: Worker, cut: int, pieces: list[int]) -> None:
    cut %= len(recording.data) + 1
    result = check(worker, recording, recording.data[:cut], pieces)
    assert [tuple(e) for e in result["events"]] == recording.stable_events(cut)
    if result["error"] is not None:
        assert result["error"]["type"] == ("NotAnRrdError" if cut == 0 else "TruncatedError"), result["error"]


@pytest.mark.timeout(120)
@FUZZ
@given(data=st.data())
def test_inserted_and_deleted_runs(recording: Recording, worker: Worker, data: st.DataObject) -> None:
    mutated = bytearray(recording.data)
    for _ in range(data.draw(st.integers(1, 4), label="edits")):
        pos = min(position(data, recording), len(mutated))
        delete = data.draw(st.integers(0, 64), label="delete")
        insert = data.draw(st.binary(max_size=64), label="insert")
        mutated[pos : pos + delete] = insert
    check(worker, recording, bytes(mutated), data.draw(pieces_strategy(), label="pieces"))


@pytest.mark.timeout(120)
@FUZZ
@given(data=st.data())
def test_duplicated_ranges(recording: Recording, worker: Worker, data: st.DataObject) -> None:
    source = recording.data
    mutated = bytearray(source)
    for _ in range(data.draw(st.integers(1, 3), label="copies")):
        start = data.draw(st.integers(0, len(source) - 1), label="start")
        length = data.draw(st.integers(1, len(source) - start), label="length")
        at = data.draw(st.integers(0, len(mutated)), label="insert at")
        mutated[at:at] = source[start : start + length]
    check(worker, recording, bytes(mutated), data.draw(pieces_strategy(), label="pieces"))


U64 = st.one_of(
    st.integers(0, 2**64 - 1),
    st.integers(0, 20_000),
    st.sampled_from(
        [0, 1, 2**31, 2**32, 2**62, 2**63, 2**64 - 1, DEFAULT_MAX_MESSAGE_SIZE, DEFAULT_MAX_MESSAGE_SIZE + 1]
    ),
)


@pytest.mark.timeout(120)
@FUZZ
@given(data=st.data())
def test_overwritten_message_headers(recording: Recording, worker: Worker, data: st.DataObject) -> None:
    """Random u64s in a message's kind or length field: a length over the limit or an unknown kind
    is reported at that message's header, everything before it is intact."""
    header = data.draw(st.sampled_from(recording.message_headers), label="message header")
    field = data.draw(st.sampled_from(["kind", "len"]), label="field")
    value = data.draw(U64, label="value")
    mutated = bytearray(recording.data)
    at = header + (0 if field == "kind" else 8)
    mutated[at : at + 8] = struct.pack("<Q", value)
    result = check(worker, recording, bytes(mutated), data.draw(pieces_strategy(), label="pieces"))
    looks_like_header = mutated[header : header + 3] == b"RRF" and mutated[header + 3 : header + 4] in b"012"
    kind, length = struct.unpack_from("<QQ", mutated, header)
    if looks_like_header:
        return
    expected = None
    if kind > 3:
        expected = "UnknownMessageKindError"
    elif length > DEFAULT_MAX_MESSAGE_SIZE:
        expected = "MessageTooLargeError"
    if expected is not None:
        assert result["error"] is not None and result["error"]["type"] == expected, result["error"]
        assert result["error"]["offset"] == header
