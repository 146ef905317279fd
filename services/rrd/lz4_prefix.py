"""The first bytes of an LZ4 block, without decompressing the rest.

A chunk's metadata (its Arrow schema, record batch header, row id and index columns) sits in the
first few kilobytes of its Arrow IPC payload; a large chunk's data columns follow. LZ4's
`LZ4_decompress_safe_partial` stops once it has produced the bytes asked for, so reading the
metadata of a 2.5 MB chunk costs a few microseconds instead of decompressing and copying all of it.

python-lz4 does not wrap that function, but its extension module carries liblz4 (statically linked
in the wheels, or linked against the system's) and exports its symbols, so it is reached with ctypes
from the very library `lz4.block` uses. Where it cannot be found, `available` is False and callers
decompress whole blocks as before (tests pin that it is found here).
"""

from __future__ import annotations

import ctypes
import logging
from collections.abc import Callable

import numpy as np

log = logging.getLogger(__name__)


def _load() -> Callable[..., int] | None:
    try:
        from lz4.block import _block

        function = ctypes.CDLL(_block.__file__).LZ4_decompress_safe_partial
    except (ImportError, OSError, AttributeError) as exc:
        log.info("LZ4 partial decompression unavailable (%s): large chunks are decompressed whole", exc)
        return None
    # int LZ4_decompress_safe_partial(const char* src, char* dst, int srcSize, int targetOutputSize, int dstCapacity)
    function.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_int]
    function.restype = ctypes.c_int
    return function


_PARTIAL = _load()
available = _PARTIAL is not None
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
