"""The agent's link reads a refusal mid-stream as a refusal, also when a write was in flight as it
came (tests/sdk_client/test_grpc_status.py has the race itself)."""

from __future__ import annotations

import asyncio

import pytest

from services.agent.link import DepotLink, DepotRefused, stream_ended
from tests.sdk_client.test_grpc_status import TRIES, WHY, refused_streams, refusing_server

pytestmark = pytest.mark.timeout(300)


async def refusals() -> tuple[list[Exception], int]:
    async with refusing_server() as port:
        link = DepotLink(f"rerun+http://127.0.0.1:{port}", "http://127.0.0.1:9", None, max_message_size=1 << 20)
        try:
            return await refused_streams(lambda: link.open_stream()[0], stream_ended)
        finally:
            await link.close()


def test_a_refusal_mid_stream_is_a_refusal_even_when_a_write_was_in_flight():
    outcomes, replaced = asyncio.run(refusals())
    assert [type(o) for o in outcomes] == [DepotRefused] * TRIES, {str(o) for o in outcomes}
    assert all(WHY in str(o) for o in outcomes)
    assert replaced > 0
