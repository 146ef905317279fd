"""`fleet retention plan|run` and `fleet catalog rebuild` (over REST, like every command but serve and db)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import click
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console

ACTIONS = ("promote", "archive", "delete", "restore")


@click.group()
def retention() -> None:
    """Tiers and expiry: what would move or go, and doing it now."""


@retention.command("plan")
@api_option
@click.option("--action", multiple=True, type=click.Choice(ACTIONS), help="only these actions (repeatable)")
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer")
def plan(api_url: str, action: tuple[str, ...], as_json: bool) -> None:
    """Print what would be promoted, archived, restored or deleted now, and why."""
    with client(api_url) as fleet:
        answer = fleet.retention_plan(list(action))
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    actions, upcoming = answer["actions"], answer.get("upcoming", [])
    console = stdout_console()
    if not actions:
        click.echo("nothing is due")
    else:
        table = Table("action", "run", "robot", "tier", "MB", "why", box=None, padding=(0, 2))
        for a in actions:
            table.add_row(a["action"], a["run"], a["robot_id"], a["tier"], f"{a['bytes'] / 1e6:,.1f}", a["reason"])
        console.print(table)
    kept = answer.get("kept", [])
    if kept:
        click.echo("kept past their policy:")
        table = Table("run", "robot", "tier", "MB", "why", box=None, padding=(0, 2))
        for k in kept:
            table.add_row(k["run"], k["robot_id"], k["tier"], f"{k['bytes'] / 1e6:,.1f}", k["reason"])
        console.print(table)
    if upcoming:
        click.echo("later:")
        table = Table("action", "run", "robot", "MB", "when", "why", box=None, padding=(0, 2))
        for u in upcoming:
            when = u["at"].replace("T", " ").replace("Z", " UTC") if u["at"] else "once it closes"
            table.add_row(u["action"], u["run"], u["robot_id"], f"{u['bytes'] / 1e6:,.1f}", when, u["reason"])
        console.print(table)


@retention.command("run")
@api_option
@click.option("--action", multiple=True, type=click.Choice(ACTIONS), help="only these actions (repeatable)")
def run(api_url: str, action: tuple[str, ...]) -> None:
    """Do what is due now, with a progress bar; exit status 1 if any run failed."""
    with client(api_url) as fleet:
        end = _follow(fleet.retention_run(list(action)), "retention")
    click.echo(f"{end.get('done', 0)} done, {end.get('failed', 0)} failed")
    if end.get("failed") or end.get("event") in ("error", "busy"):
        raise SystemExit(1)


def _follow(events: Iterator[dict[str, Any]], title: str) -> dict[str, Any]:
    """Show a progress bar over the service's NDJSON events; returns the last one."""
    err = Console(stderr=True)
    last: dict[str, Any] = {}
    with Progress(
        "{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=err, transient=True
    ) as progress:
        task = progress.add_task(title, total=None)
        for event in events:
            last = event
            kind = event.get("event")
            if kind == "plan":
                progress.update(task, total=event["total"])
            elif kind in ("done", "run"):
                progress.update(task, advance=1, description=f"{title}: {event.get('run')}")
                ok = event.get("ok", event.get("outcome") != "skipped")
                verb = event.get("action", event.get("outcome", ""))
                where = f" ({event['tier']})" if kind == "run" and event.get("tier") else ""  # scrub-secrets
                progress.console.print(
                    f"{'ok ' if ok else 'FAILED '}{verb} {event.get('run')}{where}: {event.get('detail', '')}",
                    markup=False,
                )
            elif kind in ("busy", "error"):
                progress.console.print(f"{kind}: {event.get('detail')}", markup=False)
    return last


@click.group()
def catalog() -> None:
    """The catalog as a whole."""


@catalog.command("scrub-secrets")
@api_option
@click.option("--dry-run", is_flag=True, help="only say which runs hold secret-like fields")
def scrub_secrets(api_url: str, dry_run: bool) -> None:
    """Find the hot and warm runs whose property chunks hold secret-like fields (FLEET_SECRET_FIELDS, a
    robot's `fleet` token), filed before ingest stripped them from rerun-sdk 0.23 runs and blueprints,
    and seal them again without them (same chunk ids, every other chunk as it was; a closed hot run is
    promoted first, a live one left for later). Re-runnable."""
    with client(api_url) as fleet:
        end = _follow(fleet.scrub_secrets(dry_run), "scrub-secrets")
    if end.get("event") == "error":
        raise click.ClickException(str(end.get("detail")))
    click.echo(
        f"{end.get('scrubbed', 0)} runs scrubbed, {end.get('found', 0)} found (dry run), "
        f"{end.get('clean', 0)} clean, {end.get('skipped', 0)} skipped"
    )


@catalog.command("rebuild")
@api_option
def rebuild(api_url: str) -> None:
    """Add to the catalog every sealed run found in the stores (run.json + chunks.parquet) that it
    lacks: after losing the catalog, start the service on an empty one and run this."""
    with client(api_url) as fleet:
        end = _follow(fleet.rebuild_catalog(), "rebuild")
    if end.get("event") == "error":
        raise click.ClickException(str(end.get("detail")))
    click.echo(
        f"{end.get('added', 0)} runs added, {end.get('present', 0)} already present, {end.get('skipped', 0)} skipped"
    )
