"""`fleet imports ls|show|retry|original`: uploads (RRD and MCAP) with their state, a failed MCAP
import converted again from its quarantined original, and that original fetched (admin)."""

from __future__ import annotations

import json
from pathlib import Path

import click
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console

STATES = ("receiving", "converting", "filed", "failed")


@click.group()
def imports() -> None:
    """Uploads, RRD and MCAP: their state, and why one failed."""


@imports.command("ls")
@api_option
@click.option("--state", type=click.Choice(STATES), help="only imports in this state")
@click.option("--kind", type=click.Choice(["rrd", "mcap"]), help="only uploads of this kind")
@click.option("--robot", help="only this robot's")
@click.option("--limit", type=int, default=50, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer")
def ls(api_url: str, state: str | None, kind: str | None, robot: str | None, limit: int, as_json: bool) -> None:
    """Uploads, newest first."""
    with client(api_url) as fleet:
        answer = fleet.imports(state=state, kind=kind, robot=robot, limit=limit)
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    table = Table("import", "kind", "state", "file", "MB", "runs", "new", "at", "why", box=None, padding=(0, 2))
    for i in answer["imports"]:
        table.add_row(
            i["id"],
            i["kind"],
            i["state"],
            i["name"] or "-",
            f"{i['bytes'] / 1e6:,.1f}",
            ", ".join(i["runs"]) or "-",
            f"{i['chunks_new']:,}",
            i["created_at"],
            (i["reason"] or "")[:100],
        )
    stdout_console().print(table)


@imports.command("show")
@api_option
@click.argument("import_id")
def show(api_url: str, import_id: str) -> None:
    """One import, as JSON."""
    with client(api_url) as fleet:
        click.echo(json.dumps(fleet.import_(import_id), indent=2))


@imports.command("retry")
@api_option
@click.argument("import_id")
def retry(api_url: str, import_id: str) -> None:
    """Convert a failed MCAP import again from its quarantined original (after a rerun-sdk upgrade,
    or once what stopped it is fixed)."""
    with client(api_url) as fleet:
        report = fleet.retry_import(import_id)
    imported = report.get("import") or {}
    runs = ", ".join(report.get("runs") or []) or "-"
    if report.get("already_held"):
        click.echo(f"{import_id}: run {runs}: already held (import {imported.get('held_by', '?')})")
    else:
        click.echo(f"{import_id}: filed: runs {runs}: {report.get('chunks_new', 0)} new chunks")


@imports.command("original")
@api_option
@click.argument("import_id")
@click.option("-o", "--output", "out", type=click.Path(dir_okay=False, path_type=Path), required=True)
def original(api_url: str, import_id: str, out: Path) -> None:
    """Fetch a failed MCAP import's original from quarantine (admin)."""
    with client(api_url) as fleet:
        written = fleet.import_original(import_id, out)
    click.echo(f"{out}: {written:,} bytes")
