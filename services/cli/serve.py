"""`fleet serve`: run the service on the configured addresses.

Its options are made from the depot's `Settings` (`services/cli/settings_options.py`): one per
field, named after it (`--kebab-name`), with the field's description as help and its default shown.
An option left out is None, so the environment, the TOML file and the default apply in that order
(see `load_settings`)."""

from __future__ import annotations

import socket
from typing import TYPE_CHECKING

import click

from services.cli.settings_options import SettingsCommand

if TYPE_CHECKING:
    from services.settings import Settings

# Settings that are no option of `fleet serve`, and why (shown after the options).
NOT_OPTIONS = {"retention_policies": "a list of tables: environment or TOML only"}


def _depot_settings() -> type[Settings]:
    from services.settings import Settings

    return Settings


class ServeCommand(SettingsCommand):
    settings_class = staticmethod(_depot_settings)
    not_options = NOT_OPTIONS


@click.command(cls=ServeCommand)
def serve(**flags: object) -> None:
    """Run the service. Every flag can also be set as the FLEET_* variable named in its help,
    or in a TOML file named by FLEET_CONFIG."""
    from services.auth.bootstrap import check_auth_bind
    from services.rrd import limits
    from services.server import claim_ports
    from services.settings import load_settings
    from services.startup import split_addr
    from services.workers import worker_count

    settings = load_settings(**flags)
    limits.configure(settings.max_chunk_bytes, settings.decompress_budget_bytes)  # process-wide, like the memory
    hosts = []
    for addr in (settings.http_addr, settings.grpc_addr):
        try:
            hosts.append(split_addr(addr)[0])
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from exc
    auth_off = check_auth_bind(settings, hosts)  # auth off on a public address: refused, one line
    workers = worker_count(settings)  # more than one needs a Postgres catalog: refused, one line
    # Both ports, then the data dir, before anything is printed or made: a refused start is one line
    # and leaves no data dir, catalog or start-up lines behind.
    ports = claim_ports(settings)
    try:
        _serve(settings, ports, auth_off, workers)
    finally:
        for sock in ports:
            sock.close()


def _serve(settings: Settings, ports: tuple[socket.socket, socket.socket], auth_off: str | None, workers: int) -> None:
    """`fleet serve` once its ports are bound: the data dir held, the catalog ready, the node run."""
    import asyncio
    import logging

    from catalog.db import create_engine, is_embedded, prepare_for_service
    from services.server import release_reserve_if_full
    from services.server import serve as run_server
    from services.startup import hold_data_dir
    from services.workers import run_workers

    with hold_data_dir(settings.data_dir):  # one `fleet serve` per data dir, for the process's life
        release_reserve_if_full(settings)  # a full disk must not keep the catalog from opening
        # This engine (and its pooled connection) lives as long as the service: an embedded catalog's
        # file lock is then held from the start, not from the first write an idle service may not make
        # for a while, so `fleet db upgrade` or another `fleet serve` on that file is refused at once.
        engine = create_engine(settings.catalog_url, settings.catalog_timeout_s)
        try:
            done = prepare_for_service(engine)  # a catalog that is behind: one line naming `fleet db upgrade`
            if not is_embedded(engine):
                engine.dispose()  # a shared server catalog needs no such hold
            if done:
                click.echo(f"fleet: {done}")
            logging.basicConfig(level=logging.INFO, format="%(levelname)s:     %(name)s: %(message)s")
            logging.getLogger("apscheduler").setLevel(logging.ERROR)  # not a line per job run or skipped turn
            click.echo(
                f"fleet: data in {settings.data_dir.resolve()}, REST on http://{settings.http_addr}, "
                f"Rerun gRPC on rerun+http://{settings.grpc_addr}/proxy, durability {settings.durability}"
            )
            click.echo(f"fleet: {auth_off}" if auth_off else "fleet: auth on: every request needs a token")
            login = "" if auth_off else " (log in with a token: the admin token is in DATA_DIR/admin.token)"
            click.echo(f"fleet: web console on {console_address(settings)}{login}")
            if workers > 1:
                click.echo(f"fleet: {workers} worker processes share both ports (--workers)")
                run_workers(settings, workers, ports)
            else:
                asyncio.run(run_server(settings, ports=ports))
        finally:
            engine.dispose()


def console_address(settings: Settings) -> str:
    """Where a browser on this machine (or, with `public_url`, anywhere) opens the web console."""
    from services.startup import split_addr

    if settings.public_url:
        return settings.public_url.rstrip("/") + "/console/"
    host, port = split_addr(settings.http_addr)
    if host in ("0.0.0.0", "::", ""):
        host = "localhost"
    elif ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}/console/"
