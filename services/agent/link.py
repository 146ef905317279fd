"""The agent's link to the depot: gRPC streams that carry a run's messages (as the SDK's would, with
the robot's token as metadata), and the REST calls that ask which chunks the depot holds.

The link is one gRPC channel (streams of several runs share its connection) and one REST client.
Its state is what the last call learnt: up, or down since when and why. A refusal the robot cannot
fix by waiting (a bad token, another robot's run) is `DepotRefused`: the agent retries it slowly and
says it loudly, as it may be fixed at the depot (a new token) without the agent restarting.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

import grpc
import httpx

from core.backoff import backoff_delay, jittered
from core.errors import FleetError, InvalidArgumentError
from sdk_client.grpc_status import ended, keep_status
from sdk_client.rest import FleetClient, ServiceError

log = logging.getLogger("fleet.agent")

WRITE_METHOD = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"
PROBE_METHOD = "/rerun.cloud.v1alpha1.RerunCloudService/Version"  # open, small: does the link carry data?
HELD_BATCH = 20_000  # chunk ids per question to the depot
BACKOFF_FIRST_S = 0.25
BACKOFF_MAX_S = 10.0
REFUSED_RETRY_S = 60.0
# gRPC statuses that waiting does not change: the depot refused what it was sent or who sent it.
_REFUSALS = {
    grpc.StatusCode.UNAUTHENTICATED,
    grpc.StatusCode.PERMISSION_DENIED,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.FAILED_PRECONDITION,
}


class LinkDown(Exception):
    """The depot could not be reached, or the connection broke: retry after a backoff."""


class DepotRefused(Exception):
    """The depot answered, and refused: retried slowly, said loudly."""


@dataclass(frozen=True)
class Held:
    """The depot's answer about some chunks of a run (`POST /v1/runs/RUN/held`)."""

    tier: str | None
    status: str | None
    accepts_data: bool
    missing: set[bytes] = field(default_factory=set)
    unsealed: set[bytes] = field(default_factory=set)
    holder: str | None = None  # the depot process holding its unsealed chunks (None: none does)


def grpc_target(url: str) -> tuple[str, bool]:
    """`rerun+http://HOST:PORT` -> (`HOST:PORT`, TLS or not)."""
    parts = urlsplit(url)
    if parts.scheme not in ("rerun+http", "rerun+https", "http", "https") or not parts.hostname:
        raise InvalidArgumentError(
            f"depot address {url!r} is not rerun+http://HOST:PORT (or rerun+https://): set --depot or FLEET_AGENT_DEPOT"
        )
    secure = parts.scheme.endswith("https")
    host = f"[{parts.hostname}]" if ":" in parts.hostname else parts.hostname
    return f"{host}:{parts.port or (443 if secure else 51234)}", secure


def default_api_url(depot_url: str) -> str:
    parts = urlsplit(depot_url)
    scheme = "https" if parts.scheme.endswith("https") else "http"
    host = f"[{parts.hostname}]" if parts.hostname and ":" in parts.hostname else parts.hostname
    return f"{scheme}://{host}:8080"


def channel_options(max_message_size: int, keepalive_s: float) -> list[tuple[str, int]]:
    """Keepalive pings notice a link that went silent (no reset, no answer) within a few seconds."""
    return [
        ("grpc.max_send_message_length", max_message_size + 1024),
        ("grpc.max_receive_message_length", 1 << 20),
        ("grpc.keepalive_time_ms", int(keepalive_s * 1000)),
        ("grpc.keepalive_timeout_ms", int(keepalive_s * 1000)),
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.max_pings_without_data", 0),
        ("grpc.initial_reconnect_backoff_ms", 250),
        ("grpc.max_reconnect_backoff_ms", int(BACKOFF_MAX_S * 1000)),
        ("grpc.http2.bdp_probe", 0),  # a bounded window: what a cut loses in flight stays small
    ]


class DepotLink:
    def __init__(
        self, depot_url: str, api_url: str, token: str | None, *, max_message_size: int, keepalive_s: float = 5.0
    ) -> None:
        target, secure = grpc_target(depot_url)
        self.target, self._secure = target, secure
        self._options = channel_options(max_message_size, keepalive_s)
        self.generation = 0  # counts channels: a stalled one is replaced once, by whoever notices first
        self._open_channel()
        self._metadata = (("authorization", f"Bearer {token}"),) if token else ()
        self.api = FleetClient(api_url, timeout=30.0, token=token, user="fleet-agent")
        self.up = False
        self.since = time.time()
        self.error = "not connected yet"
        self.refusals: dict[str, str] = {}  # run -> the depot's refusal, until that run's stream is taken

    def _open_channel(self) -> None:
        self.channel = (
            grpc.aio.secure_channel(self.target, grpc.ssl_channel_credentials(), options=self._options)
            if self._secure
            else grpc.aio.insecure_channel(self.target, options=self._options)
        )
        self._write = self.channel.stream_unary(WRITE_METHOD, request_serializer=None, response_deserializer=None)
        self._probe = self.channel.unary_unary(PROBE_METHOD, request_serializer=None, response_deserializer=None)

    async def close(self) -> None:
        await self.channel.close()
        self.api.close()

    def open_stream(self) -> tuple[grpc.aio.StreamUnaryCall[Any, Any], int]:
        """A new stream, and the generation of the channel it runs on."""
        return keep_status(self._write(metadata=self._metadata, wait_for_ready=False)), self.generation

    async def probe(self, timeout_s: float) -> bool:
        """Ask the depot's version on the streams' channel: an answer (any answer) within
        `timeout_s` says the link carries data. None in time on an open connection means a silent
        link, which data written into buffers would not reveal: the channel is replaced, so the
        streams on it fail and their senders connect anew and settle what was in flight."""
        generation = self.generation
        try:
            await self._probe(b"", timeout=timeout_s, metadata=self._metadata)
        except asyncio.CancelledError:
            if cancelled():
                raise
            return False  # its channel was replaced meanwhile
        except grpc.aio.AioRpcError as exc:
            if exc.code() == grpc.StatusCode.DEADLINE_EXCEEDED:
                self.mark_down(f"the depot did not answer within {timeout_s:g} s: the link is silent")
                await self.replace_channel(generation)
                return False
            if exc.code() == grpc.StatusCode.UNAVAILABLE:
                self.mark_down(f"UNAVAILABLE: {exc.details()}")
                return False
        return True

    async def replace_channel(self, generation: int) -> None:
        """The channel of `generation` took no data for too long (a silent link whose TCP connection
        still stands, which keepalives cannot see past a full send buffer): drop it, connect anew."""
        if generation != self.generation:
            return  # another stream noticed first
        self.generation += 1
        old = self.channel
        self._open_channel()
        await old.close(grace=None)

    def mark_up(self) -> None:
        """The depot answered (a refusal of a run stands until that run's stream is taken)."""
        if not self.up:
            log.info("depot link up (%s)", self.target)
            self.up, self.since = True, time.time()
        self.error = ""

    @property
    def refused(self) -> str | None:
        """The runs the depot refuses now, with why (None: none)."""
        return "; ".join(f"run {run}: {why}" for run, why in sorted(self.refusals.items())) or None

    def mark_down(self, why: str) -> None:
        if self.up:
            log.warning("depot link down: %s", why)
            self.up, self.since = False, time.time()
        self.error = why

    async def held(self, run_id: str, chunk_ids: list[bytes]) -> Held:
        """Which of `chunk_ids` the depot lacks and which it holds only unsealed (asked in batches)."""
        answer = Held(None, None, True)
        for start in range(0, max(len(chunk_ids), 1), HELD_BATCH):
            batch = [c.hex() for c in chunk_ids[start : start + HELD_BATCH]]
            body = await self.call(self.api.held, run_id, batch)
            answer = Held(
                body.get("tier"),
                body.get("status"),
                bool(body.get("accepts_data", True)),
                answer.missing | {bytes.fromhex(c) for c in body.get("missing", [])},
                answer.unsealed | {bytes.fromhex(c) for c in body.get("unsealed", [])},
                body.get("holder") or answer.holder,
            )
        return answer

    async def call(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        """A REST call off the event loop, its failures as LinkDown or DepotRefused."""
        try:
            result = await asyncio.to_thread(fn, *args, **kwargs)
        except ServiceError as exc:
            if exc.status >= 500 or exc.status == 429:
                raise LinkDown(f"depot answered {exc.status}: {exc}") from exc
            raise DepotRefused(str(exc)) from exc
        except (httpx.TransportError, FleetError) as exc:
            raise LinkDown(f"depot API unreachable ({type(exc).__name__}: {exc})") from exc
        self.mark_up()
        return result


def cancelled() -> bool:
    """Whether the running task itself is being cancelled, rather than a gRPC call it awaits (a
    call on a channel that was closed ends with CancelledError too)."""
    task = asyncio.current_task()
    return task is not None and task.cancelling() > 0


async def stream_ended(call: Any, failed: BaseException) -> Exception:
    """What a failed write or half-close of `call` means, from the status the depot sent."""
    return stream_failure(await ended(call, failed))


def stream_failure(exc: BaseException) -> Exception:
    """What a failed stream means: the depot refused it, or the link broke."""
    if isinstance(exc, grpc.aio.AioRpcError):
        if exc.code() in _REFUSALS:
            return DepotRefused(f"{exc.code().name}: {exc.details()}")
        return LinkDown(f"{exc.code().name}: {exc.details()}")
    return LinkDown(f"{type(exc).__name__}: {exc}")


class Backoff:
    """Waits that grow from a quarter second to ten, with jitter; reset by a success."""

    def __init__(self, first_s: float = BACKOFF_FIRST_S, max_s: float = BACKOFF_MAX_S) -> None:
        self.first_s, self.max_s = first_s, max_s
        self.failures = 0

    def reset(self) -> None:
        self.failures = 0

    async def wait(self, refused: bool = False) -> None:
        """After a failure: a refusal waits `REFUSED_RETRY_S` (and still counts towards the next wait)."""
        self.failures += 1
        delay = REFUSED_RETRY_S if refused else backoff_delay(self.failures, first=self.first_s, cap=self.max_s)
        await asyncio.sleep(jittered(delay))
