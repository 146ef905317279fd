"""`fleet serve`: run the service on the configured addresses."""

from __future__ import annotations

from pathlib import Path

import click


@click.command()
@click.option("--data-dir", type=click.Path(path_type=Path), help="FLEET_DATA_DIR: hot tier and embedded "
              "defaults live here; one fleet serve per data dir [default: ./fleet-data]")
@click.option("--http-addr", help="FLEET_HTTP_ADDR: REST API address [default: 0.0.0.0:8080]")
@click.option("--grpc-addr", help="FLEET_GRPC_ADDR: Rerun message proxy address [default: 0.0.0.0:51234]")
@click.option("--catalog-url", help="FLEET_CATALOG_URL: duckdb:///PATH or postgresql+psycopg://...")
@click.option("--warm-url", help="FLEET_WARM_URL: file:///PATH or s3://bucket/prefix")
@click.option("--cold-url", help="FLEET_COLD_URL: file:///PATH or s3://bucket/prefix")
@click.option("--s3-endpoint-url", help="FLEET_S3_ENDPOINT_URL: S3-compatible endpoint")
@click.option("--max-message-size", type=int, help="FLEET_MAX_MESSAGE_SIZE: largest message in bytes")
@click.option("--max-chunk-bytes", type=int, help="FLEET_MAX_CHUNK_BYTES: largest chunk once decompressed, in "
              "bytes [default: 268435456]")
@click.option("--decompress-budget-bytes", type=int, help="FLEET_DECOMPRESS_BUDGET_BYTES: decompressed chunk "
              "bytes held at once by downloads and sealing together [default: 536870912]")
@click.option("--secret-fields", help="FLEET_SECRET_FIELDS: property fields never stored nor served, "
              "comma-separated (matched as words: token matches ingest_token, apiKey matches api_key)")
@click.option("--durability", type=click.Choice(["always", "interval", "off"]),
              help="FLEET_DURABILITY: hot-tier fsync: always (before answering), interval (group commit, "
              "default), off")
@click.option("--group-commit-ms", type=int, help="FLEET_GROUP_COMMIT_MS: fsync period with durability=interval")
@click.option("--min-free-bytes", type=int, help="FLEET_MIN_FREE_BYTES: refuse new data below this free disk")
@click.option("--reserve-bytes", type=int, help="FLEET_RESERVE_BYTES: held in reserve on the data disk for the "
              "catalog, released when the disk is full; promotion never takes the disk below it")
@click.option("--max-streams", type=int, help="FLEET_MAX_STREAMS: most concurrent gRPC streams")
@click.option("--close-after-s", type=float, help="FLEET_CLOSE_AFTER_S: close a live run idle this long")
@click.option("--default-robot", help="FLEET_DEFAULT_ROBOT: robot id of runs that name none")
@click.option("--replay-bytes", type=int, help="FLEET_REPLAY_BYTES: recent live data kept for ReadMessages readers")
@click.option("--catalog-flush-s", type=float, help="FLEET_CATALOG_FLUSH_S: how often live runs reach the catalog")
@click.option("--s3-region", help="FLEET_S3_REGION: S3 region")
@click.option("--cold-storage-class", help="FLEET_COLD_STORAGE_CLASS: archive by moving warm objects to this S3 "
              "storage class (GLACIER, DEEP_ARCHIVE, STANDARD_IA) instead of copying them to the cold URL")
@click.option("--promote-after-s", type=float, help="FLEET_PROMOTE_AFTER_S: seal a closed run idle this long "
              "into the warm tier [default: 600]")
@click.option("--promote-below-free-bytes", type=int, help="FLEET_PROMOTE_BELOW_FREE_BYTES: hot high-water mark; "
              "below this free disk, closed runs are promoted oldest first at once")
@click.option("--warm-days", type=float, help="FLEET_WARM_DAYS: default policy, days warm before archiving")
@click.option("--cold-days", type=float, help="FLEET_COLD_DAYS: default policy, days cold before deletion")
@click.option("--restore-days", type=float, help="FLEET_RESTORE_DAYS: a restored run serves this many days")
@click.option("--promote-interval-s", type=float, help="FLEET_PROMOTE_INTERVAL_S: how often promotion runs")
@click.option("--retention-interval-s", type=float, help="FLEET_RETENTION_INTERVAL_S: how often archive, "
              "restore and expiry run")
@click.option("--scheduler/--no-scheduler", default=None, help="FLEET_SCHEDULER: run the retention jobs here "
              "[default: on]. Overrides by robot or application: FLEET_RETENTION_POLICIES or TOML.")
@click.option("--sql-max-rows", type=int, help="FLEET_SQL_MAX_ROWS: most rows a SQL answer may have")
@click.option("--sql-timeout-s", type=float, help="FLEET_SQL_TIMEOUT_S: a SQL query running longer is stopped")
@click.option("--sql-memory-limit", help="FLEET_SQL_MEMORY_LIMIT: memory a SQL query's worker process may use "
              "(e.g. 2GB)")
@click.option("--sql-threads", type=int, help="FLEET_SQL_THREADS: threads a SQL query may use")
@click.option("--sql-workers", type=int, help="FLEET_SQL_WORKERS: SQL queries running at once [default: 2]")
@click.option("--sql-queue", type=int, help="FLEET_SQL_QUEUE: SQL queries waiting for a worker; more get 429 "
              "[default: 8]")
def serve(**flags: object) -> None:
    """Run the service. Every flag can also be set as the FLEET_* variable named in its help,
    or in a TOML file named by FLEET_CONFIG."""
    import asyncio
    import logging

    from catalog.db import create_engine, is_embedded, prepare_for_service
    from services.rrd import limits
    from services.server import release_reserve_if_full, split_addr
    from services.server import serve as run_server
    from services.settings import load_settings
    from services.startup import hold_data_dir

    settings = load_settings(**flags)
    limits.configure(settings.max_chunk_bytes, settings.decompress_budget_bytes)  # process-wide, like the memory
    for addr in (settings.http_addr, settings.grpc_addr):
        try:
            split_addr(addr)
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from exc
    with hold_data_dir(settings.data_dir):  # one `fleet serve` per data dir, for the process's life
        release_reserve_if_full(settings)  # a full disk must not keep the catalog from opening
        # This engine (and its pooled connection) lives as long as the service: an embedded catalog's
        # file lock is then held from the start, not from the first write an idle service may not make
        # for a while, so `fleet db upgrade` or another `fleet serve` on that file is refused at once.
        engine = create_engine(settings.catalog_url)
        try:
            done = prepare_for_service(engine)  # a catalog that is behind: one line naming `fleet db upgrade`
            if not is_embedded(engine):
                engine.dispose()  # a shared server catalog needs no such hold
            if done:
                click.echo(f"fleet: {done}")
            logging.basicConfig(level=logging.INFO, format="%(levelname)s:     %(name)s: %(message)s")
            logging.getLogger("apscheduler").setLevel(logging.ERROR)  # not a line per job run or skipped turn
            click.echo(f"fleet: data in {settings.data_dir.resolve()}, REST on http://{settings.http_addr}, "
                       f"Rerun gRPC on rerun+http://{settings.grpc_addr}/proxy, durability {settings.durability}")
            asyncio.run(run_server(settings))
        finally:
            engine.dispose()
