"""Large bodies handed to the HTTP server in slices (services/runs/sending.py): the same bytes in
the same order, no slice above the size, and slices are views of the pieces, not copies."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

from services.runs.sending import in_slices


async def _collect(body: AsyncIterator[bytes | memoryview]) -> list[bytes | memoryview]:
    return [piece async for piece in body]


def test_a_synchronous_body_comes_in_slices_that_are_views_of_its_pieces():
    pieces = [bytes(range(256)) * 10, b"small", b"x" * 1000]
    got = asyncio.run(_collect(in_slices(iter(pieces), size=1000)))
    assert b"".join(bytes(p) for p in got) == b"".join(pieces)
    assert [len(p) for p in got] == [1000, 1000, 560, 5, 1000]
    assert isinstance(got[0], memoryview) and got[0].obj is pieces[0]  # sliced, not copied
    assert got[3] is pieces[1]  # a small piece goes as it is


def test_an_asynchronous_body_is_sliced_alike():
    async def body() -> AsyncIterator[bytes]:
        yield b"a" * 2500
        yield b"b"

    got = asyncio.run(_collect(in_slices(body(), size=1000)))
    assert [bytes(p) for p in got] == [b"a" * 1000, b"a" * 1000, b"a" * 500, b"b"]
