"""`fleet upload FILE...`: send .rrd files (a robot's FileSink copies) to the service."""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.progress import Progress, TaskID

from services.cli.client import api_option, client
from services.cli.output import transfer_progress


@click.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--run-id", help="MCAP files: the run to file them as (default: their metadata's, else from their digest)"
)
@click.option("--application", help="MCAP files: their application id (default: mcap)")
@click.option(
    "--robot", help="MCAP files: their robot, with a write token (default: the token's, else their metadata's)"
)
@api_option
def upload(
    files: tuple[Path, ...], run_id: str | None, application: str | None, robot: str | None, api_url: str
) -> None:
    """Upload .rrd or MCAP FILES (ROS 2 bags, Foxglove recordings: the depot converts them with
    Rerun's own loader). Chunks the service already holds (received live) are skipped, and an MCAP
    file it holds is filed once, so uploading the same file again is harmless; a file that shares no
    chunk with a run that already has data (rerun-sdk 0.23's second recording beside a live stream)
    is warned about. With auth on: a `write` token, or a robot's `ingest` token for that robot's
    runs. `fleet imports ls` lists uploads and why one failed."""
    from sdk_client.rest import ServiceError

    console = Console(stderr=True)
    failed = 0
    with (
        client(api_url) as fleet,
        transfer_progress(console) as progress,
    ):
        for path in files:
            task = progress.add_task(path.name, total=os.path.getsize(path))
            try:
                report = fleet.upload(
                    path,
                    functools.partial(_advance, progress, task),
                    run_id=run_id,
                    application=application,
                    robot=robot,
                )
            except ServiceError as exc:
                if exc.status == 401:
                    raise  # no file would go: one line about the token, not one per file
                failed += 1
                kept = kept_note(exc.body.get("accepted") or {})
                progress.console.print(f"Error: {path}: {exc}{kept}", style="red", markup=False, soft_wrap=True)
                continue
            finally:
                progress.remove_task(task)
            click.echo(f"{path}: {summary(report)}")
            for warning in report.get("warnings", []):
                progress.console.print(f"Warning: {path}: {warning}", style="yellow", markup=False, soft_wrap=True)
    if failed:
        raise SystemExit(1)


def summary(report: dict[str, Any]) -> str:
    """One line of what an upload filed."""
    runs = ", ".join(report["runs"]) or "-"
    imported = report.get("import") or {}
    if report.get("already_held"):
        return f"run {runs}: already held (import {imported.get('held_by', '?')}), nothing new"
    line = (
        f"runs {runs}: {report['chunks_new']} new chunks ({report['bytes_new']:,} bytes), "
        f"{report['chunks_duplicate']} already held"
    )
    if imported.get("kind") == "mcap":
        line += f" (MCAP converted, import {imported['id']})"
    return line


def kept_note(accepted: dict[str, Any]) -> str:
    """What a refused upload left on the depot, as the depot reports it: a run refused part-way
    (another robot's) is dropped whole, so only the runs still named hold what came before."""
    if not accepted:
        return ""
    dropped, runs = accepted.get("dropped") or [], accepted.get("runs") or []
    parts = [f"run {', '.join(dropped)} dropped whole: nothing of it is kept"] if dropped else []
    if runs or not dropped:
        parts.append(
            f"what came before it is kept: {accepted.get('chunks_new', 0)} new chunks"
            f"{' in ' + ', '.join(runs) if runs else ''}, {accepted.get('chunks_duplicate', 0)} already held"
        )
    return f" ({'; '.join(parts)})"


def _advance(progress: Progress, task: TaskID, count: int) -> None:
    progress.update(task, advance=count)
