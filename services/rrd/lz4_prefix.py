"""The first bytes of an LZ4 block, without decompressing the rest; or all of it into a buffer
that is used again (`decompress_into`).

A chunk's metadata (its Arrow schema, record batch header, row id and index columns) sits in the
first few kilobytes of its Arrow IPC payload; a large chunk's data columns follow. LZ4's
`LZ4_decompress_safe_partial` stops once it has produced the bytes asked for, so reading the
metadata of a 2.5 MB chunk costs a few microseconds instead of decompressing and copying all of it.

python-lz4 does not wrap that function, but its extension module carries liblz4 (statically linked
in the wheels, or linked against the system's) and exports its symbols, so it is reached with ctypes
from the very library `lz4.block` uses. Where it cannot be found, `available` is False and callers
decompress whole blocks as before (tests pin that it is found here).

A whole block decompressed only to be checked and dropped (ingest's check of a large chunk) goes
into a buffer kept per thread (`decompress_into`): `lz4.block` allocates a new one for every block,
and on this machine the page faults of a fresh 2.5 MB allocation cost 14 times the decompression
(5.4 ms against 0.37 ms a chunk of benchmarks/data/big.rrd).
"""

from __future__ import annotations

import ctypes
import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, cast

import numpy as np

log = logging.getLogger(__name__)


def _load(name: str, arguments: int) -> Callable[..., int] | None:
    try:
        from lz4.block import _block

        function: Any = getattr(ctypes.CDLL(_block.__file__), name)
    except (ImportError, OSError, AttributeError) as exc:
        log.info("%s unavailable (%s): large chunks are decompressed whole, by lz4.block", name, exc)
        return None
    function.argtypes = [ctypes.c_void_p, ctypes.c_void_p, *[ctypes.c_int] * (arguments - 2)]
    function.restype = ctypes.c_int
    return cast(Callable[..., int], function)


# int LZ4_decompress_safe_partial(const char* src, char* dst, int srcSize, int targetOutputSize, int dstCapacity)
_PARTIAL = _load("LZ4_decompress_safe_partial", 5)
# int LZ4_decompress_safe(const char* src, char* dst, int compressedSize, int dstCapacity)
_WHOLE = _load("LZ4_decompress_safe", 4)
available = _PARTIAL is not None and _WHOLE is not None
_INT_MAX = 2**31 - 1


class PrefixTooShort(Exception):
    """Reading needs the payload's bytes up to `end`; only a shorter prefix was decompressed."""

    def __init__(self, end: int) -> None:
        super().__init__(end)
        self.end = end


def decompress_prefix(block: bytes | bytearray | memoryview, size: int) -> bytes:
    """The first `size` bytes the LZ4 block decompresses to. Raises ValueError if the block is
    malformed before that point or decompresses to fewer bytes (only what precedes them is checked:
    the rest of the block is not read)."""
    if _PARTIAL is None:
        raise RuntimeError("LZ4 partial decompression is unavailable")
    if not 0 < size <= _INT_MAX or len(block) > _INT_MAX:
        raise ValueError(f"cannot decompress {size} bytes of a block of {len(block)}")
    source = np.frombuffer(block, dtype=np.uint8)  # its address, without copying a read-only buffer
    out = ctypes.create_string_buffer(size)
    got = _PARTIAL(source.ctypes.data, out, len(block), size, size)
    if got < 0:
        raise ValueError(f"LZ4 block malformed within its first {size} decompressed bytes")
    if got != size:
        raise ValueError(f"LZ4 block decompressed to {got} bytes, fewer than the {size} asked for")
    return out.raw


class _Scratch(threading.local):
    buffer: bytearray | None = None
    address: int = 0


_scratch = _Scratch()
SCRATCH_MAX_BYTES = 64 * 1024 * 1024  # larger blocks get a buffer of their own, dropped after use


@contextmanager
def decompress_into(block: bytes | bytearray | memoryview, size: int) -> Iterator[memoryview]:
    """The `size` bytes the LZ4 block decompresses to, as a view of this thread's buffer, valid until
    the block leaves: ValueError unless the whole block is sound and gives exactly `size` bytes.
    Whoever holds a part of the view past it (a numpy array, a slice) must drop it first."""
    if _WHOLE is None:
        raise RuntimeError("LZ4 decompression into a buffer is unavailable")
    if not 0 < size <= _INT_MAX or len(block) > _INT_MAX:
        raise ValueError(f"cannot decompress {size} bytes of a block of {len(block)}")
    if size > SCRATCH_MAX_BYTES:
        buffer, address = _buffer(size)
    else:
        if _scratch.buffer is None or len(_scratch.buffer) < size:
            _scratch.buffer, _scratch.address = _buffer(max(size, 1 << 20))
        buffer, address = _scratch.buffer, _scratch.address
    source = np.frombuffer(block, dtype=np.uint8)  # its address, without copying a read-only buffer
    got = _WHOLE(source.ctypes.data, address, len(block), size)
    if got != size:
        raise ValueError(
            "LZ4 block malformed" if got < 0 else f"LZ4 block decompressed to {got} bytes, declared {size}"
        )
    with memoryview(buffer) as whole, whole[:size] as view:
        yield view


def _buffer(size: int) -> tuple[bytearray, int]:
    buffer = bytearray(size)
    return buffer, ctypes.addressof(ctypes.c_char.from_buffer(buffer))
