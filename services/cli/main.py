"""`fleet`: the command line of the fleet telemetry depot."""

from __future__ import annotations

import sys

import click

from services import __version__
from services.cli.agent import agent
from services.cli.analytics import analytics
from services.cli.datasets import datasets
from services.cli.db import db
from services.cli.events import events, runs_annotate, runs_tag, runs_untag
from services.cli.imports import imports
from services.cli.mcp import mcp
from services.cli.retention import catalog, retention
from services.cli.rrd import rrd
from services.cli.rules import rules
from services.cli.rules_backfill import backfill
from services.cli.runs import download, runs, view
from services.cli.serve import serve
from services.cli.sql import sql
from services.cli.tokens import tokens
from services.cli.upload import upload
from services.cli.webhooks import webhooks


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="fleet")
def cli() -> None:
    """Fleet telemetry depot for robots that log with Rerun."""


cli.add_command(serve)
cli.add_command(rrd)
cli.add_command(db)
cli.add_command(upload)
cli.add_command(imports)
cli.add_command(runs)
cli.add_command(download)
cli.add_command(view)
cli.add_command(retention)
cli.add_command(catalog)
cli.add_command(sql)
cli.add_command(analytics)
cli.add_command(mcp)
cli.add_command(tokens)
cli.add_command(agent)
rules.add_command(backfill)
cli.add_command(rules)
cli.add_command(events)
runs.add_command(runs_annotate)
runs.add_command(runs_tag)
runs.add_command(runs_untag)
cli.add_command(webhooks)
cli.add_command(datasets)


def main() -> None:
    """Errors users can fix are one line on stderr and exit status 1, never a traceback."""
    from pydantic import ValidationError

    from core.errors import FleetError

    try:
        cli()
    except FleetError as exc:
        click.echo(f"Error: {exc}", err=True)
        sys.exit(1)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}" for e in exc.errors())
        click.echo(f"Error: invalid settings: {problems}", err=True)
        sys.exit(1)
