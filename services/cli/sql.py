"""`fleet sql "QUERY"`: read-only SQL over the catalog and the analytics tables (over REST)."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console

FORMATS = ("table", "json", "csv", "arrow", "parquet")


@click.command()
@api_option
@click.argument("query")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(FORMATS),
    default="table",
    show_default=True,
    help="table (for people), or the service's json, csv, arrow (IPC stream) or parquet",
)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), help="write the answer here")
def sql(api_url: str, query: str, fmt: str, output: Path | None) -> None:
    """Run QUERY (one SELECT) over robots, runs, run_entities, run_timelines, run_metrics, events,
    run_tags, scalars, text_logs and transforms. Example: fleet sql "SELECT robot_id, count(*) FROM runs GROUP BY 1" """
    with client(api_url) as fleet:
        if fmt == "table":
            from services.analytics.service import textual

            answer = textual(fleet.sql(query))
            table = Table(*answer.column_names, box=None, padding=(0, 2))
            for row in answer.to_pylist() if answer.num_rows <= 10_000 else answer.slice(0, 10_000).to_pylist():
                table.add_row(*("" if v is None else str(v) for v in row.values()))
            stdout_console().print(table)
            click.echo(f"({answer.num_rows:,} rows)", err=True)
            return
        data = fleet.sql_bytes(query, fmt)
    if output is not None:
        output.write_bytes(data)
        click.echo(f"{output}: {len(data):,} bytes", err=True)
    elif fmt in ("arrow", "parquet") and sys.stdout.isatty():
        raise click.ClickException(f"{fmt} is binary: write it to a file with -o FILE")
    else:
        sys.stdout.buffer.write(data)
