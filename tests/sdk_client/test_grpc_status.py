"""A stream the server refuses mid-way ends with the server's status, also when grpc.aio replaces it
with its own INTERNAL "Internal error from Core": a write still in flight as the refusal arrived
fails after it, and grpc.aio's `set_internal_error` overwrites the status (7 to 43 of 300 refusals
of a writing client here). The tests make that overwrite with grpc.aio's own call, on a real
call the server refused, so that they do not wait on the race."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import grpc
import pytest

from sdk_client.grpc_status import FAILED_IN_CORE, ended, keep_status, server_status

SERVICE, METHOD = "rerun.sdk_comms.v1alpha1.MessageProxyService", "WriteMessages"
WHY = "another robot's run"


async def refuse_the_first(requests: AsyncIterator[bytes], context: grpc.aio.ServicerContext[Any, Any]) -> bytes:
    async for _ in requests:
        context.set_trailing_metadata((("fleet-error-code", "PERMISSION_DENIED"),))
        await context.abort(grpc.StatusCode.PERMISSION_DENIED, WHY)
    return b""


@asynccontextmanager
async def refusing_server() -> AsyncIterator[int]:
    """A gRPC server on loopback whose WriteMessages refuses each stream at its first message."""
    server = grpc.aio.server()
    handler = grpc.stream_unary_rpc_method_handler(refuse_the_first)
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE, {METHOD: handler}),))
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        yield port
    finally:
        await server.stop(None)


async def refused_and_overwritten(call: Any) -> grpc.aio.AioRpcError:
    """Write a message into `call`, which the server refuses; then overwrite its status as grpc.aio
    does when a write fails after the status came. What the call itself says after that."""
    await call.write(b"m")
    with pytest.raises(grpc.aio.AioRpcError) as refused:
        await call
    assert refused.value.code() == grpc.StatusCode.PERMISSION_DENIED
    call._cython_call.set_internal_error("a write failed in core")  # what grpc.aio's `_write` does
    with pytest.raises(grpc.aio.AioRpcError) as overwritten:
        await call
    assert (overwritten.value.code(), overwritten.value.details()) == (grpc.StatusCode.INTERNAL, FAILED_IN_CORE)
    return overwritten.value


async def outcomes() -> tuple[Any, Any, Any]:
    async with refusing_server() as port, grpc.aio.insecure_channel(f"127.0.0.1:{port}") as channel:
        write = channel.stream_unary(f"/{SERVICE}/{METHOD}")
        kept = keep_status(write())
        overwritten = await refused_and_overwritten(kept)
        plain = write()  # not kept: nothing to go back to
        plain_overwritten = await refused_and_overwritten(plain)
        return (
            await ended(kept, overwritten),
            server_status(kept, overwritten),
            server_status(plain, plain_overwritten),
        )


def test_the_server_s_refusal_is_what_a_kept_stream_ended_with():
    awaited, looked_up, not_kept = asyncio.run(outcomes())
    for status in (awaited, looked_up):
        assert (status.code(), status.details()) == (grpc.StatusCode.PERMISSION_DENIED, WHY)
        assert dict(status.trailing_metadata())["fleet-error-code"] == "PERMISSION_DENIED"
    assert not_kept.code() == grpc.StatusCode.INTERNAL  # a call not kept has only grpc.aio's word


def test_a_failure_with_no_status_in_time_is_the_failure_itself():
    async def hung() -> BaseException:
        never: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        failed = TimeoutError("the write took no data")
        return await ended(never, failed, wait_s=0.01)

    assert isinstance(asyncio.run(hung()), TimeoutError)
