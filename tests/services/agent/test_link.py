"""The agent's link reads a refusal mid-stream as a refusal, also when grpc.aio replaced the
depot's status with its own INTERNAL after a write that was in flight as it came
(tests/sdk_client/test_grpc_status.py)."""

from __future__ import annotations

import asyncio

from services.agent.link import DepotLink, DepotRefused, LinkDown, stream_ended, stream_failure
from tests.sdk_client.test_grpc_status import WHY, refused_and_overwritten, refusing_server


async def outcome() -> tuple[Exception, Exception]:
    async with refusing_server() as port:
        link = DepotLink(f"rerun+http://127.0.0.1:{port}", "http://127.0.0.1:9", None, max_message_size=1 << 20)
        try:
            call, _generation = link.open_stream()
            overwritten = await refused_and_overwritten(call)
            return await stream_ended(call, overwritten), stream_failure(overwritten)
        finally:
            await link.close()


def test_a_refusal_mid_stream_is_a_refusal_even_when_a_write_was_in_flight():
    ended, as_grpc_said = asyncio.run(outcome())
    assert isinstance(ended, DepotRefused)
    assert WHY in str(ended)
    assert isinstance(as_grpc_said, LinkDown)  # what the agent made of it before
