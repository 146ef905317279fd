"""`fleet db ...`: the catalog database schema."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    import sqlalchemy as sa


def _engine(catalog_url: str | None) -> sa.Engine:
    from catalog.db import create_engine
    from services.settings import load_settings

    return create_engine(load_settings(catalog_url=catalog_url).catalog_url)


@click.group()
def db() -> None:
    """The catalog database schema (migrations)."""


_url_option = click.option("--catalog-url", help="FLEET_CATALOG_URL: duckdb:///PATH or postgresql+psycopg://...")


@db.command()
@_url_option
def upgrade(catalog_url: str | None) -> None:
    """Bring the catalog schema to the version this release needs."""
    from catalog.db import upgrade as upgrade_catalog

    engine = _engine(catalog_url)
    try:
        before, after = upgrade_catalog(engine)
    finally:
        engine.dispose()
    if before == after:
        click.echo(f"catalog already at revision {after}")
    else:
        click.echo(f"catalog upgraded from revision {before or '(empty)'} to {after}")


@db.command()
@_url_option
def current(catalog_url: str | None) -> None:
    """Show the catalog's schema revision and the one this release needs."""
    from catalog.db import current_revision, head_revision

    engine = _engine(catalog_url)
    try:
        click.echo(f"catalog at {current_revision(engine) or '(empty)'}, this release needs {head_revision()}")
    finally:
        engine.dispose()


@db.command()
@_url_option
def recount(catalog_url: str | None) -> None:
    """Count again what the catalog counts as runs are written (the columns of each dataset's segment
    table), from the runs themselves: after a rolling upgrade, whose nodes of the older release
    wrote runs without counting them."""
    from sqlalchemy.orm import Session

    from catalog.dataset_columns import refill
    from catalog.db import check_schema

    engine = _engine(catalog_url)
    try:
        check_schema(engine)
        with Session(engine) as session, session.begin():
            runs = refill(session)
    finally:
        engine.dispose()
    click.echo(f"counted the dataset columns of {runs:,} runs again")
