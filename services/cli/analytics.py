"""`fleet analytics ...`: the analytics tables as the lakehouse's Iceberg tables (docs/lakehouse.md).

Run on a host with the depot's settings (FLEET_* or FLEET_CONFIG), like `fleet db`: it works on the
catalog database and the warm store directly, beside a running depot or without one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    from services.lakehouse.sync import SyncReport


@click.group()
def analytics() -> None:
    """The analytics tables as Iceberg tables that outside engines read (the lakehouse)."""


_url_option = click.option("--catalog-url", help="FLEET_CATALOG_URL: duckdb:///PATH or postgresql+psycopg://...")


@analytics.command()
@_url_option
@click.option(
    "--batches", type=click.IntRange(min=1), help="stop after this many batches (of 32 runs); run again to go on"
)
def migrate(catalog_url: str | None, batches: int | None) -> None:
    """Copy every run's analytics rows held before the lakehouse into its tables, with progress.

    Each run's Parquet files are read by ranged reads and their rows appended to the Iceberg tables
    (with the robot and date they were filed under, which the files hold only in their path); runs the
    tables hold already are skipped. Safe to stop and run again, and beside running depots: a run is
    never copied twice."""
    from sqlalchemy.orm import sessionmaker

    from catalog import lakehouse as marks
    from catalog.db import check_schema, create_engine, session_scope
    from core.clock import utcnow
    from services.lakehouse.sync import sync
    from services.lakehouse.tables import open_lakehouse
    from services.sealed.tiers import open_tiers
    from services.settings import load_settings

    settings = load_settings(**({"catalog_url": catalog_url} if catalog_url else {}))
    if not settings.lakehouse:
        raise click.ClickException("the lakehouse is turned off (FLEET_LAKEHOUSE=false): turn it on first")
    engine = create_engine(settings.catalog_url)
    try:
        check_schema(engine)
        catalog = sessionmaker(engine)
        warm = open_tiers(settings).warm
        lake = open_lakehouse(settings.catalog_url, warm)
        try:
            with session_scope(catalog, write=True) as session:
                marked = marks.queue_all(session)
            click.echo(f"{marked:,} runs to copy")

            def progress(report: SyncReport) -> None:
                click.echo(f"copied {report.runs:,} runs ({report.rows:,} rows), removed {report.removed:,}")

            report = sync(lake, catalog, warm, utcnow, batches=batches, progress=progress)
        finally:
            lake.close()
    finally:
        engine.dispose()
    left = f", {report.left:,} left: run it again to go on" if report.left else ""
    click.echo(f"done: {report.runs:,} runs copied, {report.rows:,} rows{left}")
