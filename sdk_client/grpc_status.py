"""The status a client's gRPC stream ended with, as the server sent it.

grpc.aio replaces a stream's status with its own INTERNAL "Internal error from Core" when a write
fails in the client's core after the server's answer arrived: a write still in flight as the server
refused the stream mid-way (7 to 43 of 300 refusals of a writing client here). The server's refusal
would then read as a broken call, retried as one. `keep_status` records the status a call first
ends with; `ended` gives the server's status of a failed write or half-close.

The first status is read from the call's `_cython_call._status`, which grpc.aio itself reads to
raise; tests/sdk_client/test_grpc_status.py pins it against a real server.
"""

from __future__ import annotations

import asyncio
import weakref
from typing import Any, TypeVar

import grpc

FAILED_IN_CORE = "Internal error from Core"
STATUS_WAIT_S = 2.0

E = TypeVar("E", bound=BaseException)
C = TypeVar("C")

_first: weakref.WeakKeyDictionary[Any, grpc.aio.AioRpcError] = weakref.WeakKeyDictionary()


def keep_status(call: C) -> C:
    """`call`, its first status kept as it arrives."""
    call.add_done_callback(_keep)  # type: ignore[attr-defined]
    return call


def _keep(call: Any) -> None:
    status = getattr(getattr(call, "_cython_call", None), "_status", None)
    if status is not None:
        _first[call] = grpc.aio.AioRpcError(
            _code(status.code()),
            grpc.aio.Metadata(),
            grpc.aio.Metadata.from_tuple(status.trailing_metadata() or ()),
            details=status.details(),
            debug_error_string=status.debug_error_string(),
        )


def _code(value: int) -> grpc.StatusCode:
    return next((code for code in grpc.StatusCode if code.value[0] == value), grpc.StatusCode.UNKNOWN)


def server_status(call: Any, error: E) -> grpc.aio.AioRpcError | E:
    """`error`, or the status the server sent if grpc.aio replaced it after a failed write."""
    replaced = (
        isinstance(error, grpc.aio.AioRpcError)
        and error.code() == grpc.StatusCode.INTERNAL
        and error.details() == FAILED_IN_CORE
    )
    return _first.get(call, error) if replaced else error


async def ended(call: Any, failed: E, wait_s: float = STATUS_WAIT_S) -> grpc.aio.AioRpcError | E:
    """Why a write or half-close of `call` failed: the stream's status, which arrives within moments
    of the failure and says why (a refusal), or the failure itself if none comes in `wait_s`."""
    try:
        await asyncio.wait_for(call, wait_s)
    except grpc.aio.AioRpcError as status:
        return server_status(call, status)
    except Exception:  # no status in time: the failure is all there is
        pass
    return server_status(call, failed)
