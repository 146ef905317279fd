"""How FetchChunks reads a run: neighbouring chunks in one read, reads under way at once, and a
first response that does not wait for the rest (on a recording of frames made here, read through
a function that records and can hold back each read)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import pytest

from services.redap import chunks
from services.redap.keys import ChunkLocation
from services.rrd.frames import MESSAGE_HEADER_SIZE, MessageKind, encode_message_header
from services.rrd.protowire import fields
from services.runs.indexed import GAP_BYTES, IndexedRecording
from tests.waiting import wait_for


def frame(kind: MessageKind, size: int, fill: int) -> bytes:
    return encode_message_header(kind, size) + bytes([fill]) * size


def recording(sizes_and_gaps: list[tuple[int, int]]) -> tuple[bytes, list[ChunkLocation]]:
    """Chunk frames of the given payload sizes, each after a frame of another kind of the given size
    (0: none): the file and where its chunks are."""
    data, found = bytearray(), []
    for n, (size, gap) in enumerate(sizes_and_gaps):
        if gap:
            data += frame(MessageKind.SET_STORE_INFO, gap - MESSAGE_HEADER_SIZE, 0)
        found.append(ChunkLocation("run", len(data), size + MESSAGE_HEADER_SIZE))
        data += frame(MessageKind.ARROW_MSG, size, n + 1)
    return bytes(data), found


def opened(data: bytes, read: Callable[[int, int], bytes], depth: int) -> dict[str, IndexedRecording]:
    return {"run": IndexedRecording(read, len(data), lambda: [], read_ahead=depth)}


def messages(answer: bytes) -> list[bytes]:
    """The ArrowMsg bytes of one FetchChunksResponse (field 1, each)."""
    return [answer[start:end] for number, _, start, end in fields(answer) if number == 1]


def recorded(data: bytes) -> tuple[list[tuple[int, int]], Callable[[int, int], bytes]]:
    """A read of `data` that records each (offset, length) asked for, and its record."""
    reads: list[tuple[int, int]] = []

    def read(offset: int, length: int) -> bytes:
        reads.append((offset, length))
        return data[offset : offset + length]

    return reads, read


def test_chunks_closer_than_the_gap_are_read_together_and_farther_ones_apart():
    data, wanted = recording([(100, 0), (200, GAP_BYTES), (300, GAP_BYTES + 1), (50, 0)])
    reads, read = recorded(data)
    answers = list(chunks._responses(wanted, opened(data, read, 1)))
    got = [m for answer in answers for m in messages(answer)]
    assert got == [data[w.offset + MESSAGE_HEADER_SIZE : w.end] for w in wanted]
    # The first two with the 64 KiB between them; the third, past the gap, with the fourth beside it.
    assert reads == [
        (wanted[0].offset, wanted[1].end - wanted[0].offset),
        (wanted[2].offset, wanted[3].end - wanted[2].offset),
    ]


def test_reads_are_merged_up_to_the_read_size(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(chunks, "READ_BYTES", 1000)
    data, wanted = recording([(400, 0)] * 5)
    reads, read = recorded(data)
    list(chunks._responses(wanted, opened(data, read, 1)))
    assert [length for _, length in reads] == [2 * 416, 2 * 416, 416]


def test_the_first_read_is_small_and_each_next_twice_the_last(monkeypatch: pytest.MonkeyPatch):
    # The first response is out soon, even of large chunks; then reads grow to the read size.
    monkeypatch.setattr(chunks, "FIRST_READ_BYTES", 1000)
    monkeypatch.setattr(chunks, "READ_BYTES", 4000)
    data, wanted = recording([(400, 0)] * 20)
    reads, read = recorded(data)
    answers = list(chunks._responses(wanted, opened(data, read, 1)))
    assert [length // 416 for _, length in reads] == [2, 4, 9, 5]
    assert len(messages(answers[0])) == 2  # the first read's chunks, at once


def test_a_chunk_larger_than_the_first_read_is_read_alone(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(chunks, "FIRST_READ_BYTES", 1000)
    data, wanted = recording([(3000, 0), (100, 0), (100, 0)])
    reads, read = recorded(data)
    list(chunks._responses(wanted, opened(data, read, 1)))
    assert reads == [(wanted[0].offset, wanted[0].length), (wanted[1].offset, wanted[2].end - wanted[1].offset)]


def test_the_first_response_goes_while_later_reads_are_under_way():
    # Far apart: one read each. The reads after the first are held back until the first response
    # is in: it must not wait for them, and they must already be under way.
    data, wanted = recording([(1000, 0)] + [(1000, 2 * GAP_BYTES)] * 5)
    first_offset = wanted[0].offset
    released = threading.Event()
    started: list[int] = []
    finished: list[int] = []
    lock = threading.Lock()

    def read(offset: int, length: int) -> bytes:
        with lock:
            started.append(offset)
        if offset != first_offset:
            released.wait(10)
        with lock:
            finished.append(offset)
        return data[offset : offset + length]

    answers = chunks._responses(wanted, opened(data, read, 4))
    try:
        first = next(answers)
        with lock:
            assert finished == [first_offset]  # the first response did not wait for any other read
        # Four reads under way at once: the three held back all start (a pool thread may take a
        # moment to pick one up) while none has finished.
        wait_for(lambda: len(started) == 4, 10, "four reads under way", interval=0.005)
        assert finished == [first_offset]
        assert messages(first) == [data[first_offset + MESSAGE_HEADER_SIZE : wanted[0].end]]
    finally:
        released.set()
    rest = [m for answer in answers for m in messages(answer)]
    assert rest == [data[w.offset + MESSAGE_HEADER_SIZE : w.end] for w in wanted[1:]]
