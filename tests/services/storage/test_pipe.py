"""The bounded pipe between a writer thread and a reader (an upload): bytes in order, memory
bounded, the writer's failure raised to the reader, the reader's giving up stopping the writer."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from services.storage.pipe import WRITE_PIECE, Pipe, PipeAbandonedError


def test_what_is_written_is_read_in_order_and_the_writer_waits_for_room() -> None:
    data = os.urandom(5 * WRITE_PIECE + 123)
    pipe = Pipe(max_bytes=2 * WRITE_PIECE)
    most_held: list[int] = []

    def write() -> None:
        for start in range(0, len(data), 1000):  # small writes, as the encoder makes
            pipe.write(data[start : start + 1000])
            most_held.append(pipe._held)
        pipe.close()

    with ThreadPoolExecutor(1) as pool:
        writing = pool.submit(write)
        got = bytearray()
        while piece := pipe.read(777_777):
            got += piece
        writing.result()
    assert bytes(got) == data
    assert max(most_held) <= 2 * WRITE_PIECE + WRITE_PIECE  # bounded (a piece may exceed what is left)


def test_read_all_and_a_closed_pipe_reads_its_end() -> None:
    pipe = Pipe()
    pipe.write(b"abc")
    pipe.write(b"def")
    pipe.close()
    assert pipe.read() == b"abcdef"
    assert pipe.read(10) == b""


def test_the_writers_failure_is_raised_to_the_reader() -> None:
    pipe = Pipe()
    pipe.write(b"x" * WRITE_PIECE)  # handed over
    pipe.fail(ValueError("chunk 7 is damaged"))
    with pytest.raises(ValueError, match="chunk 7"):
        pipe.read(2 * WRITE_PIECE)


def test_a_reader_that_gives_up_stops_a_waiting_writer() -> None:
    pipe = Pipe(max_bytes=WRITE_PIECE)
    started = threading.Event()

    def write() -> None:
        started.set()
        while True:  # the pipe fills, then the writer waits until the reader gives up
            pipe.write(b"y" * WRITE_PIECE)

    with ThreadPoolExecutor(1) as pool:
        writing = pool.submit(write)
        assert started.wait(10)
        pipe.abandon()
        with pytest.raises(PipeAbandonedError):
            writing.result(timeout=10)
