"""`fleet serve`: the REST API and the gRPC message proxy in one process, one event loop."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import socket
from pathlib import Path

import grpc
import uvicorn
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine
from services import __version__
from services.analytics.service import Analytics
from services.analytics.sql import Limits
from services.api.app import create_app
from services.api.grpc_front import Front
from services.auth.bootstrap import ensure_admin_token, open_auth
from services.auth.links import MaskLinkSignatures
from services.hot.reserve import DiskReserve
from services.hot.store import HotStore
from services.ingest import grpc_handler
from services.ingest.identity import SecretFields
from services.ingest.replay import ReplayHub
from services.ingest.service import IngestService
from services.redap import grpc_handler as redap_handler
from services.redap.depot import Depot
from services.retention.schedule import start_scheduler
from services.retention.service import Retention
from services.runtime import tune_allocator
from services.sealed.tiers import open_tiers, sealed_lookup
from services.settings import Settings
from services.startup import listen_grpc, listen_http, private_socket_path, release_private_socket, split_addr

log = logging.getLogger("fleet")


def build(settings: Settings) -> tuple[IngestService, Retention, Analytics]:
    """The ingest, retention and analytics sides of one node, sharing the catalog and the stores."""
    hot = HotStore(
        settings.hot_dir,
        durability=settings.durability,
        interval_ms=settings.group_commit_ms,
        min_free_bytes=settings.min_free_bytes,
    )
    catalog = sessionmaker(create_engine(settings.catalog_url))
    tiers = open_tiers(settings)
    replay = ReplayHub(settings.replay_bytes) if settings.replay_bytes else None
    ingest = IngestService(
        hot,
        catalog,
        default_robot=settings.default_robot,
        max_streams=settings.max_streams,
        close_after=dt.timedelta(seconds=settings.close_after_s),
        replay=replay,
        sealed_lookup=sealed_lookup(catalog, tiers),
        secret_fields=SecretFields(settings.secret_fields),
    )
    retention = Retention(
        catalog,
        tiers,
        settings.policies,
        ingest,
        promote_after=dt.timedelta(seconds=settings.promote_after_s),
        promote_below_free_bytes=settings.promote_below_free_bytes,
        restore_days=settings.restore_days,
        reserve_bytes=settings.reserve_bytes,
    )
    analytics = Analytics(
        catalog,
        tiers.warm,
        Limits(
            settings.sql_max_rows,
            settings.sql_timeout_s,
            settings.sql_memory_limit,
            settings.sql_threads,
            settings.sql_workers,
            settings.sql_queue,
        ),
    )
    return ingest, retention, analytics


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


def _claim_ports(settings: Settings) -> tuple[socket.socket, socket.socket]:
    """Both ports, before any recovery work: a refused start is one line, quick, and changes nothing."""
    grpc_socket = listen_grpc(*split_addr(settings.grpc_addr))
    try:
        http_socket = listen_http(*split_addr(settings.http_addr))
    except Exception:
        grpc_socket.close()
        raise
    return grpc_socket, http_socket


def _grpc_server(settings: Settings) -> tuple[grpc.aio.Server, str]:
    """The gRPC server, on a private Unix socket behind the public port's front."""
    path = str(private_socket_path(settings.data_dir))
    server = grpc.aio.server(options=grpc_handler.server_options(settings.max_message_size))
    server.add_insecure_port(f"unix:{path}")
    return server, path


async def serve(settings: Settings) -> None:
    """Run the node until stopped; the caller holds the data dir (`startup.hold_data_dir`)."""
    tune_allocator()
    grpc_socket, http_socket = _claim_ports(settings)
    grpc_server, grpc_path = _grpc_server(settings)
    ingest, retention, analytics = build(settings)
    auth = open_auth(settings, ingest.catalog)
    admin = await asyncio.to_thread(ensure_admin_token, auth, settings.data_dir)
    if admin is not None:  # shown this once; kept in the data dir for CLI commands on this machine
        print(
            f"fleet: first start: an admin token was made (shown once, also in {settings.data_dir / 'admin.token'}):\n"
            f"{admin.token}",
            flush=True,
        )
    recovered = ingest.recover()
    if recovered:
        log.info("recovered %d hot runs", len(recovered))
    ingest.hot.start()
    grpc_handler.add_to_server(
        grpc_server,
        grpc_handler.MessageProxy(
            ingest, auth, token_wait_s=settings.auth_wait_s, token_buffer_bytes=settings.auth_buffer_bytes
        ),
    )
    redap_handler.add_to_server(
        grpc_server,
        redap_handler.CatalogServer(Depot(retention.catalog, retention.tiers.warm, ingest, settings.public_url), auth),
    )
    app = create_app(settings, ingest, retention, analytics, auth)
    http = uvicorn.Server(uvicorn.Config(app, log_level="info", lifespan="off"))
    logging.getLogger("uvicorn.access").addFilter(MaskLinkSignatures())  # a link's signature opens it
    await grpc_server.start()
    front = Front(grpc_socket, grpc_path, f"fleet-telemetry {__version__}")
    front.start()
    reserve = DiskReserve(settings.data_dir, settings.reserve_bytes)
    await asyncio.to_thread(reserve.ensure)
    housekeeping = asyncio.create_task(_housekeeping(ingest, reserve, settings.catalog_flush_s))
    scheduler = (
        start_scheduler(retention, settings.promote_interval_s, settings.retention_interval_s)
        if settings.scheduler
        else None
    )
    try:
        await http.serve(sockets=[http_socket])
    finally:
        if scheduler is not None:
            scheduler.shutdown(wait=True)
        housekeeping.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await housekeeping
        await front.stop()
        await grpc_server.stop(grace=5)
        release_private_socket(Path(grpc_path), settings.data_dir)
        ingest.close()
        analytics.close()  # its idle query workers and their scratch folders
