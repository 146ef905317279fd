"""`/metrics`: the Prometheus exposition, every metric with HELP and TYPE.

The ingest figures live in the ingest service (plain counters it updates as streams and uploads
end); a custom collector reads them at scrape time, so nothing is counted twice and ingest has no
dependency on the Prometheus client. HTTP requests (among them SQL queries and retention runs
asked for over REST) are counted by an ASGI middleware, by route template, as they are answered.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services import __version__
from services.auth.tokens import Auth
from services.corpus.live import LiveRules
from services.edge import triggers
from services.ingest.service import IngestService
from services.runs import served

CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4  # the text format every Prometheus server reads

# ingest.totals key -> HELP text; a key added there later still gets a counter with a generic HELP.
INGEST_TOTALS_HELP = {
    "chunks_new": "Chunks stored for the first time (counted when their stream or upload ends)",
    "chunks_duplicate": "Chunks received that the depot already held, skipped (counted when their stream or "
    "upload ends)",
    "bytes_new": "Bytes of chunks stored for the first time (counted when their stream or upload ends)",
    "bytes_duplicate": "Bytes of chunks received that the depot already held (counted when their stream or "
    "upload ends)",
    "messages": "RRD messages received over gRPC and uploads (counted when their stream or upload ends)",
}


class IngestCollector(Collector):
    """This node's ingest figures, read from the service at each scrape."""

    def __init__(self, ingest: IngestService | None) -> None:
        self.ingest = ingest

    def collect(self) -> Iterator[Metric]:
        yield InfoMetricFamily("fleet_build", "The running release", value={"version": __version__})
        ingest = self.ingest
        if ingest is None:
            return
        yield GaugeMetricFamily("fleet_live_streams", "gRPC WriteMessages streams open now", value=ingest.live_streams)
        hot_runs, live_runs = ingest.run_counts()
        yield GaugeMetricFamily("fleet_hot_runs", "Runs held in this node's hot tier", value=hot_runs)
        yield GaugeMetricFamily("fleet_live_runs", "Hot runs still being written to", value=live_runs)
        for key, value in ingest.totals.items():
            help_text = INGEST_TOTALS_HELP.get(key, f"Ingest total {key.replace('_', ' ')}")
            yield CounterMetricFamily(f"fleet_ingest_{key}", help_text, value=value)


class LiveRulesCollector(Collector):
    """What the running rules cost this node as hot runs' chunks arrive (services/corpus/live.py),
    read at each scrape; nothing when the node runs no live rules."""

    def __init__(self, ingest: IngestService | None) -> None:
        self.ingest = ingest

    def collect(self) -> Iterator[Metric]:
        live = self.ingest.observer if self.ingest is not None else None
        if not isinstance(live, LiveRules):
            return
        yield CounterMetricFamily(
            "fleet_live_rules_cpu_seconds",
            "CPU time the live rules' worker spent evaluating hot runs' chunks and writing their results",
            value=live.cpu_s,
        )
        yield CounterMetricFamily(
            "fleet_live_rules_chunks", "Chunks of hot runs evaluated by the live rules", value=live.evaluated_chunks
        )
        yield CounterMetricFamily(
            "fleet_live_rules_dropped_chunks",
            "Chunks not evaluated live because the rules' queue was full (their runs are evaluated again at sealing)",
            value=live.dropped_chunks,
        )


class AuthCollector(Collector):
    """Refused requests and streams, by surface (rest, grpc, stream, link) and reason (missing,
    invalid, expired, revoked, forbidden), read from the token service at each scrape."""

    def __init__(self, auth: Auth) -> None:
        self.auth = auth

    def collect(self) -> Iterator[Metric]:
        family = CounterMetricFamily(
            "fleet_auth_failures",
            "Requests and streams refused for want of a valid token or scope, by surface and reason",
            labels=["surface", "reason"],
        )
        for (surface, reason), count in sorted(self.auth.failures.items()):
            family.add_metric([surface, reason], count)
        yield family


class TriggerCollector(Collector):
    """Trigger pulls made in this process, by who queued them (robot: reported by the agent that
    fired the trigger; depot: queued by the live rules), read at each scrape."""

    def collect(self) -> Iterator[Metric]:
        family = CounterMetricFamily(
            "fleet_trigger_pulls",
            "Trigger pulls made: windows around events asked of robots' agents, by who queued them",
            labels=["origin"],
        )
        for origin in (triggers.DEPOT, triggers.ROBOT):
            family.add_metric([origin], triggers.trigger_pulls_made[origin])
        yield family


class CatalogChunksCollector(Collector):
    """Chunks the catalog server served, by how: through this process (FetchChunks), or handed out
    as presigned URLs into the warm bucket for the client to read (FLEET_DIRECT_READS=presigned)."""

    def collect(self) -> Iterator[Metric]:
        chunks = CounterMetricFamily(
            "fleet_catalog_chunks_served",
            "Chunks served to catalog clients, by how: depot (FetchChunks) or direct (read from the bucket by a "
            "presigned URL)",
            labels=["how"],
        )
        sizes = CounterMetricFamily(
            "fleet_catalog_chunk_bytes_served",
            "Bytes of chunks served to catalog clients, by how (as chunks_served)",
            labels=["how"],
        )
        for how in served.HOW:
            chunks.add_metric([how], served.served[(how, "chunks")])
            sizes.add_metric([how], served.served[(how, "bytes")])
        yield chunks
        yield sizes


def metrics_registry(ingest: IngestService | None, auth: Auth | None = None) -> CollectorRegistry:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(IngestCollector(ingest))
    registry.register(TriggerCollector())
    registry.register(LiveRulesCollector(ingest))
    registry.register(CatalogChunksCollector())
    if auth is not None:
        registry.register(AuthCollector(auth))
    return registry


# A scrape's own thread: in the loop's default executor it would wait behind every catalog call of
# a burst of streams opening (200 at once kept a scrape waiting over 10 s, Prometheus's default
# scrape timeout), and scrapes are what operators read exactly then.
_SCRAPES = ThreadPoolExecutor(max_workers=1, thread_name_prefix="metrics-scrape")


async def exposition(registry: CollectorRegistry) -> bytes:
    """HELP and TYPE lines, then the samples, for every metric of the registry (off the event loop,
    on the scrapes' own thread)."""
    return await asyncio.get_running_loop().run_in_executor(_SCRAPES, generate_latest, registry)


class RequestMetrics:
    """Pure ASGI middleware (a streamed download passes through untouched): each HTTP request
    counted by method, route template and status, and its time to the response's first byte.
    Paths that match no route share the route "unmatched", so a scan of URLs adds no series."""

    def __init__(self, app: ASGIApp, registry: CollectorRegistry) -> None:
        self.app = app
        self.requests = Counter(
            "fleet_http_requests",
            "HTTP requests answered, by method, route template and status",
            ["method", "route", "status"],
            registry=registry,
        )
        self.seconds = Histogram(
            "fleet_http_request_seconds",
            "Time from an HTTP request to its response's headers, by method and route template",
            ["method", "route"],
            registry=registry,
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500  # what the server answers when the app raises before starting a response

        async def answered(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                self.seconds.labels(scope["method"], _route(scope)).observe(time.perf_counter() - started)
            await send(message)

        try:
            await self.app(scope, receive, answered)
        finally:
            self.requests.labels(scope["method"], _route(scope), str(status)).inc()


def _route(scope: Scope) -> str:
    route: Any = scope.get("route")  # set by the router on the scope it was given (this one)
    return str(getattr(route, "path", "unmatched"))
