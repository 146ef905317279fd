"""A run's file read around the page cache: every byte as the file holds it, whatever the reads'
sizes and wherever they stop between the device's blocks; the page cache left as it was; and the
same bytes through the page cache where direct reads are refused."""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from services.hot.direct import ALIGN, DirectFile
from tests.services.hot.page_cache import direct_reads_work, resident_bytes, uncache

MAX_READ = 64 * 1024


@pytest.fixture
def data_file(tmp_path: Path) -> tuple[Path, bytes]:
    data = os.urandom(40 * ALIGN + 123)  # ends between blocks
    path = tmp_path / "run.rrd"
    path.write_bytes(data)
    return path, data


def _read_all(reader: DirectFile, sizes: list[int]) -> bytes:
    got = bytearray()
    for i in range(1_000_000):  # bounded: a reader that never ends fails the test, not the run
        piece = reader.read(sizes[i % len(sizes)])
        if not piece:
            break
        assert len(piece) <= sizes[i % len(sizes)]
        got += piece
    return bytes(got)


@pytest.mark.parametrize(
    "sizes", [[MAX_READ], [1], [ALIGN - 1, 3 * ALIGN + 5, 17], [MAX_READ + ALIGN + 1], [ALIGN * 7]]
)
def test_every_byte_is_read_as_the_file_holds_it(data_file: tuple[Path, bytes], sizes: list[int]) -> None:
    path, data = data_file
    reader = DirectFile(path, MAX_READ)
    try:
        assert _read_all(reader, sizes) == data
        assert reader.read(MAX_READ) == b""  # after the end
        assert reader.position == len(data)
    finally:
        reader.close()
    reader.close()  # twice: nothing more to close


def test_what_is_read_stays_out_of_the_page_cache(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    data = os.urandom(4 * 1024 * 1024)
    path.write_bytes(data)
    uncache(path)
    if resident_bytes(path) > len(data) // 2:
        pytest.skip("this file system keeps the file cached whatever is asked (tmpfs)")
    if not direct_reads_work(path):
        pytest.skip(f"the file system under {tmp_path} refuses direct reads")
    reader = DirectFile(path, MAX_READ)
    try:
        assert reader.direct
        assert _read_all(reader, [MAX_READ]) == data
    finally:
        reader.close()
    assert resident_bytes(path) < len(data) // 8, "the read went through the page cache"


def _refusing(real: Callable[..., Any], when: Callable[..., bool]) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        if when(*args):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(*args, **kwargs)

    return call


def test_a_file_system_without_direct_reads_is_read_through_the_cache(
    data_file: tuple[Path, bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    path, data = data_file
    flag = getattr(os, "O_DIRECT", 0)
    monkeypatch.setattr(os, "open", _refusing(os.open, lambda _path, flags, *_: bool(flags & flag)))
    reader = DirectFile(path, MAX_READ)
    try:
        assert not reader.direct
        assert _read_all(reader, [ALIGN - 1, MAX_READ]) == data
    finally:
        reader.close()


def test_a_device_that_refuses_the_blocks_read_is_read_through_the_cache(
    data_file: tuple[Path, bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Direct reads opened, then refused (a device whose blocks are larger than ALIGN): the reader
    goes on through the page cache from where it was."""
    path, data = data_file
    calls = [0]

    def second_read(*_: Any) -> bool:
        calls[0] += 1
        return calls[0] == 2

    monkeypatch.setattr(os, "preadv", _refusing(os.preadv, second_read))
    if not direct_reads_work(path):
        pytest.skip(f"the file system under {path.parent} refuses direct reads")
    reader = DirectFile(path, MAX_READ)
    try:
        assert _read_all(reader, [3 * ALIGN + 1]) == data
        assert calls[0] >= 2 and not reader.direct
    finally:
        reader.close()
