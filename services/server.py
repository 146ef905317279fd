"""`fleet serve`: the REST API and the gRPC message proxy in one process, one event loop."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import socket
from dataclasses import dataclass
from pathlib import Path

import grpc
import pyarrow as pa
import uvicorn
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine
from core.errors import ConflictError
from services import __version__
from services.analytics.service import Analytics
from services.analytics.sql import Limits
from services.api import peer
from services.api.app import create_app
from services.api.grpc_front import Front
from services.api.h2_writes import WriteServer
from services.api.http_protocol import BoundedHttpToolsProtocol
from services.auth.bootstrap import announce_admin, ensure_admin_token, open_auth
from services.auth.links import MaskLinkSignatures
from services.cluster.ownership import Ownership
from services.cluster.relay import Channels, peer_channel_options
from services.compiled import compiled_summary
from services.console import app as console
from services.corpus.pipeline import BACKFILL_JOB, CorpusPipeline, corpus_pipeline
from services.datasets import exports as dataset_exports
from services.datasets.resolve import Sources as DatasetSources
from services.facts.identity import SecretFields
from services.hot.reserve import DiskReserve
from services.hot.store import HotStore
from services.imports.records import Ledger, purge_quarantine, recover_interrupted
from services.ingest import grpc_handler
from services.ingest.replay import ReplayHub
from services.ingest.service import IngestService
from services.lakehouse import maintenance
from services.lakehouse import sync as lakehouse_sync
from services.lakehouse.tables import open_lakehouse
from services.mcp_server import http as mcp_http
from services.node import Node
from services.redap import grpc_handler as redap_handler
from services.redap.dataframe import dataframe_part, read_dataframe_part
from services.redap.depot import Depot
from services.redap.keys import key_column
from services.retention.schedule import Job, node_name, start_scheduler
from services.retention.service import Retention
from services.routine_logs import quiet_routine_requests
from services.runs import totals
from services.runs.latest_at import may_keep
from services.runtime import freeze_startup_objects, tune_allocator
from services.sealed.index import CHUNK, ComponentRange, IndexRow, TimelineRange, read_index, to_parquet
from services.sealed.tiers import open_tiers, sealed_lookup
from services.settings import Settings
from services.startup import (
    listen_grpc,
    listen_http,
    listen_unix,
    private_socket_path,
    release_private_socket,
    split_addr,
    worker_socket_path,
)
from services.webhooks.deliver import deliver_due
from services.webhooks.service import Webhooks
from services.webhooks.silent import silent_pass

log = logging.getLogger("fleet")


def shared_catalog(settings: Settings) -> bool:
    """A catalog many depot processes share (Postgres): runs then have owners. The embedded DuckDB
    catalog has a single writer process, which files every run itself."""
    return not settings.catalog_url.startswith("duckdb:")


def node_id(settings: Settings) -> str:
    """FLEET_NODE_ID, else this host's name and the REST port: unique among the processes of one
    host (no two share a port) and the same after a restart, so a node finds its runs again."""
    return settings.node_id or f"{socket.gethostname()}-{split_addr(settings.http_addr)[1]}"


def advertised(settings: Settings, port: int) -> str:
    """The peer address other nodes are told: FLEET_PEER_ADVERTISE, else the bind host (this host's
    name when that is a wildcard), with the port bound."""
    host = settings.peer_advertise or split_addr(settings.peer_addr)[0]
    if host in ("0.0.0.0", "::", ""):
        host = socket.gethostname()
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def open_node(settings: Settings, peer_addr: str | None = None) -> Node:
    """What the sides of one node share: its catalog, stores, clock and auth, and (`peer_addr`:
    where this node's peer port is reached, when many nodes share the catalog) its run ownership
    and channels to the other nodes."""
    catalog = sessionmaker(create_engine(settings.catalog_url, settings.catalog_timeout_s))
    ownership = Ownership(catalog, node_id(settings), peer_addr, settings.lease_s, __version__) if peer_addr else None
    tiers = open_tiers(settings)
    return Node(
        settings=settings,
        catalog=catalog,
        tiers=tiers,
        hot=HotStore(
            settings.hot_dir,
            durability=settings.durability,
            interval_ms=settings.group_commit_ms,
            min_free_bytes=settings.min_free_bytes,
        ),
        auth=open_auth(settings, catalog),
        default_robot=settings.default_robot,
        secret_fields=SecretFields(settings.secret_fields),
        ownership=ownership,
        channels=Channels(peer_channel_options(settings.max_message_size)) if ownership else None,
        lakehouse=open_lakehouse(settings.catalog_url, tiers.warm) if settings.lakehouse else None,
    )


@dataclass(frozen=True)
class Sides:
    """One node and its ingest, retention and analytics sides, built on it."""

    node: Node
    ingest: IngestService
    retention: Retention
    analytics: Analytics
    corpus: CorpusPipeline


def build(settings: Settings, peer_addr: str | None = None) -> Sides:
    """The node (`open_node`) and its ingest, retention and analytics sides."""
    node = open_node(settings, peer_addr)
    corpus = corpus_pipeline(node)
    ingest = IngestService(
        node.hot,
        node.catalog,
        default_robot=node.default_robot,
        max_streams=settings.max_streams,
        close_after=dt.timedelta(seconds=settings.close_after_s),
        clock=node.clock,
        replay=ReplayHub(settings.replay_bytes) if settings.replay_bytes else None,
        sealed_lookup=sealed_lookup(node.catalog, node.tiers),
        secret_fields=node.secret_fields,
        ownership=node.ownership,
        channels=node.channels,
        observer=corpus.live,
    )
    corpus.attach(ingest)
    retention = Retention(
        node,
        settings.policies,
        ingest,
        promote_after=dt.timedelta(seconds=settings.promote_after_s),
        promote_below_free_bytes=settings.promote_below_free_bytes,
        restore_days=settings.restore_days,
        reserve_bytes=settings.reserve_bytes,
        on_sealed=corpus.sealing.sealed,
    )
    limits = Limits(
        settings.sql_max_rows,
        settings.sql_timeout_s,
        settings.sql_memory_limit,
        settings.sql_threads,
        settings.sql_workers,
        settings.sql_queue,
        settings.sql_read_ahead_files,
    )
    return Sides(node, ingest, retention, Analytics(node, limits), corpus)


def release_reserve_if_full(settings: Settings) -> bool:
    """Before the catalog is opened: on a full disk, give the catalog the space held in reserve."""
    return DiskReserve(settings.data_dir, settings.reserve_bytes).release_if_full()


async def _housekeeping(ingest: IngestService, reserve: DiskReserve, every: float) -> None:
    """Close idle runs and write what changed to the catalog, every `every` seconds; hold the disk
    reserve again once there is room. Catalog and disk work runs on worker threads so that ingest
    never waits for the database."""
    while True:
        await asyncio.sleep(every)
        ingest.close_idle()
        records = ingest.take_dirty_records()
        try:
            await asyncio.to_thread(ingest.save_records, records)
        except Exception as exc:
            log.warning(
                "catalog update failed (%s: %s); the runs are safe on disk, retrying",
                type(exc).__name__,
                str(exc).splitlines()[0][:200] if str(exc) else "",
            )
        if not reserve.held:
            await asyncio.to_thread(reserve.ensure)


async def _heartbeat(ownership: Ownership) -> None:
    """Tell the catalog this node is alive, three times per lease: its runs stay its own."""
    while True:
        await asyncio.sleep(ownership.lease_s / 3)
        try:
            await asyncio.to_thread(ownership.heartbeat)
        except Exception as exc:
            log.warning("heartbeat not written (%s); this node's runs pass to others after FLEET_LEASE_S", exc)


def webhook_jobs(hooks: Webhooks, ingest: IngestService) -> list[Job]:
    """The webhooks' passes, run by the one schedule: deliveries due, and robots gone silent."""
    every = hooks.settings.webhook_interval_s
    silent_check_s = max(1.0, min(30.0, hooks.settings.silent_after_s / 4))
    return [
        Job("webhooks", lambda _: deliver_due(hooks), every),
        # a silence is seen within a quarter of FLEET_SILENT_AFTER_S (at most 30 s) of its start
        Job("robot.silent", lambda _: silent_pass(hooks, ingest.hot_runs()), silent_check_s),
    ]


def lakehouse_jobs(node: Node) -> list[Job]:
    """The lakehouse's jobs: sealed runs' rows copied to its Iceberg tables (`services.lakehouse.sync`),
    and their upkeep (`services.lakehouse.maintenance`)."""
    lake = node.lakehouse
    if lake is None:
        return []
    settings, warm = node.settings, node.tiers.warm
    keep = dt.timedelta(seconds=settings.lakehouse_keep_s)

    def sync(_: object) -> lakehouse_sync.SyncReport:
        return lakehouse_sync.sync(lake, node.catalog, warm, node.clock, batches=lakehouse_sync.JOB_BATCHES)

    def upkeep(_: object) -> maintenance.MaintenanceReport:
        return maintenance.maintain(lake, warm, node.clock(), keep)

    return [
        Job(lakehouse_sync.JOB, sync, settings.lakehouse_sync_s),
        Job(maintenance.JOB, upkeep, settings.lakehouse_maintenance_s),
    ]


def export_job(node: Node, ingest: IngestService) -> Job:
    """Dataset exports queued for the depot, run one at a time per process (`services.datasets.exports`)."""
    settings = node.settings
    sources = DatasetSources(node.catalog, node.tiers.warm, ingest, node.clock)
    places = dataset_exports.Places.of(settings)
    return Job(
        dataset_exports.JOB, lambda _: dataset_exports.run_due(sources, places, node_name()), settings.export_interval_s
    )


def warm_up() -> None:
    """Pay at start what a run's first window, manifest or chunk fetch after a restart would: modules
    imported on first use (NumPy's masked arrays, Arrow's datasets) and the first calls of Arrow's
    Parquet, IPC and compute kernels, LZ4 and the plan of a window, tens of milliseconds in all, on
    a chunk index of a few rows made here."""
    rows = [
        IndexRow(
            CHUNK,
            "recording",
            16 * n,
            16,
            bytes([n]) * 16,
            f"/warm/{n % 2}",
            False,
            10,
            (TimelineRange("frame", "sequence", 10 * n, 10 * n + 9),),
            ("Scalars",),
            (ComponentRange("Scalars", "frame", 10 * n, 10 * n + 9, 10),),
        )
        for n in range(4)
    ]
    index = read_index(to_parquet(rows))
    index.timeline_types(), index.entity_paths()
    by_entity, _, _ = index.groups()
    may_keep(index, by_entity["/warm/1"], "frame", (25, 26), True)
    keys = key_column("warm-up", [row.offset for row in rows], [row.length for row in rows], [r.chunk_id for r in rows])
    read_dataframe_part(dataframe_part(pa.table({"chunk_key": keys})))


async def _recover_imports(node: Node) -> None:
    """Uploads this node was receiving or converting when it stopped, failed saying so (a catalog
    that does not answer yet leaves them for the next start: nothing else waits on them)."""
    try:
        await asyncio.to_thread(recover_interrupted, Ledger.of(node), node.settings.data_dir / "imports")
    except Exception as exc:
        log.warning("interrupted imports not checked at start (%s: %s)", type(exc).__name__, exc)


def claim_ports(settings: Settings) -> tuple[socket.socket, socket.socket]:
    """Both ports, before any recovery work: a refused start is one line, quick, and changes nothing."""
    grpc_socket = listen_grpc(*split_addr(settings.grpc_addr))
    try:
        http_socket = listen_http(*split_addr(settings.http_addr))
    except Exception:
        grpc_socket.close()
        raise
    return grpc_socket, http_socket


def _grpc_server(settings: Settings) -> tuple[grpc.aio.Server, str, str | None]:
    """The gRPC server, on a private Unix socket behind the public port's front, and on the peer
    port when many nodes share the catalog (returns where other nodes reach that)."""
    path = str(private_socket_path(settings.data_dir))
    # No SO_REUSEPORT: a second process binding the same peer port must fail, not share it.
    options = [*grpc_handler.server_options(settings.max_message_size), ("grpc.so_reuseport", 0)]
    server = grpc.aio.server(options=options)
    server.add_insecure_port(f"unix:{path}")
    if not shared_catalog(settings):
        return server, path, None
    host, port = split_addr(settings.peer_addr)
    try:
        bound = server.add_insecure_port(f"[{host}]:{port}" if ":" in host else f"{host}:{port}")
    except RuntimeError:
        raise ConflictError(
            f"the peer address {settings.peer_addr} cannot be used (in use?): set another with --peer-addr "
            "or FLEET_PEER_ADDR"
        ) from None
    return server, path, advertised(settings, bound)


def add_services(
    server: grpc.aio.Server,
    proxy: grpc_handler.MessageProxy,
    catalog_server: redap_handler.CatalogServer,
    peers: peer.PeerService | None,
) -> None:
    """Every gRPC service a node answers, on its private socket (behind the public port's front) and
    its peer port. tests/services/test_client_inputs.py lists their methods through this: each
    must be in its table of client inputs, with its hostile requests."""
    grpc_handler.add_to_server(server, proxy)
    redap_handler.add_to_server(server, catalog_server)
    if peers is not None:
        peer.add_to_server(server, peers)


async def serve(
    settings: Settings,
    sockets: tuple[socket.socket, socket.socket] | None = None,
    siblings: list[Path] | None = None,
    *,
    ports: tuple[socket.socket, socket.socket] | None = None,
) -> None:
    """Run the node until stopped; the caller holds the data dir (`startup.hold_data_dir`).
    `sockets`: the gRPC and REST ports, bound already and shared with other workers of this host
    (`services.workers`, which also made the first admin token); `siblings`: those workers' private
    REST sockets (for /metrics of the whole host). `ports`: both ports of a single node, claimed
    by its caller (`fleet serve` claims them first of all, so a busy one is refused before anything)."""
    tune_allocator()
    grpc_socket, http_socket = sockets or ports or claim_ports(settings)
    grpc_server, grpc_path, peer_addr = _grpc_server(settings)
    sides = build(settings, peer_addr)
    node, ingest, retention, analytics = sides.node, sides.ingest, sides.retention, sides.analytics
    corpus = sides.corpus
    if node.ownership is not None:
        await asyncio.to_thread(node.ownership.start)
        log.info("node %s on a shared catalog, peer port %s", node.ownership.node_id, peer_addr)
    if sockets is None:  # workers: the first admin token was made before they started
        announce_admin(await asyncio.to_thread(ensure_admin_token, node.auth, settings.data_dir), settings.data_dir)
    log.info("ingest path: %s", compiled_summary())
    recovered = ingest.recover()
    if recovered:
        log.info("recovered %d hot runs", len(recovered))
    node.hot.start()
    await asyncio.to_thread(corpus.start)
    proxy = grpc_handler.MessageProxy(
        ingest,
        node.auth,
        token_wait_s=settings.auth_wait_s,
        token_buffer_bytes=settings.auth_buffer_bytes,
        token_buffer_total_bytes=settings.auth_buffer_total_bytes,
    )
    app = create_app(node, ingest, retention, analytics)
    console.install(app)
    assistants = mcp_http.install(app)  # /mcp: the MCP server for AI assistants (docs/mcp.md)
    app.state.rules_backfill = corpus.backfill  # POST /v1/rules/backfill
    catalog_server = redap_handler.CatalogServer(Depot(node, ingest), node.auth)
    # other nodes read the hot runs this one owns
    peers = peer.PeerService(node, ingest, app.state.edge) if node.ownership is not None else None
    add_services(grpc_server, proxy, catalog_server, peers)
    http_sockets = [http_socket]
    if sockets is not None:  # a worker: its own REST socket too, where its siblings ask for its figures
        http_sockets.append(listen_unix(worker_socket_path(settings.data_dir)))
        app.state.sibling_sockets = siblings or []
    http = uvicorn.Server(uvicorn.Config(app, http=BoundedHttpToolsProtocol, log_level="info", lifespan="off"))
    logging.getLogger("uvicorn.access").addFilter(MaskLinkSignatures())  # a link's signature opens it
    quiet_routine_requests()  # an agent's pull polls and copy reports: DEBUG, not a line every 5 s
    await grpc_server.start()
    writes = WriteServer(proxy.write_messages, settings.max_message_size)
    front = Front(grpc_socket, grpc_path, f"fleet-telemetry {__version__}", writes)
    front.start()
    reserve = DiskReserve(settings.data_dir, settings.reserve_bytes)
    await asyncio.to_thread(reserve.ensure)
    housekeeping = asyncio.create_task(_housekeeping(ingest, reserve, settings.catalog_flush_s))
    heartbeat = asyncio.create_task(_heartbeat(node.ownership)) if node.ownership is not None else None
    await _recover_imports(node)
    scheduler = (
        start_scheduler(
            retention,
            settings.promote_interval_s,
            settings.retention_interval_s,
            settings.lease_s if node.ownership is not None else None,
            [
                *webhook_jobs(app.state.webhooks, ingest),
                Job(BACKFILL_JOB, lambda _: corpus.backfill.run(), settings.rules_backfill_interval_s),
                export_job(node, ingest),
                Job("fleet.totals", lambda _: totals.count_job(node.catalog, node.clock()), totals.COUNT_INTERVAL_S),
                *lakehouse_jobs(node),
                Job(
                    "imports.quarantine", lambda _: purge_quarantine(node.catalog, node.tiers.warm, node.clock()), 3600
                ),
            ],
        )
        if settings.scheduler
        else None
    )
    await asyncio.to_thread(warm_up)
    freeze_startup_objects()
    try:
        async with assistants:
            await http.serve(sockets=http_sockets)
    finally:
        if scheduler is not None:
            scheduler.shutdown(wait=True)
        for task in (housekeeping, heartbeat):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        if node.channels is not None:
            await node.channels.close()
        await front.stop()
        await grpc_server.stop(grace=5)
        release_private_socket(Path(grpc_path), settings.data_dir)
        corpus.stop()
        ingest.close()
        analytics.close()  # its idle query workers and their scratch folders
