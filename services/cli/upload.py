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
@api_option
def upload(files: tuple[Path, ...], api_url: str) -> None:
    """Upload .rrd FILES. Chunks the service already holds (received live) are skipped, so
    uploading the same file again is harmless; a file that shares no chunk with a run that already
    has data (rerun-sdk 0.23's second recording beside a live stream) is warned about. With auth
    on: a `write` token, or a robot's `ingest` token for that robot's runs."""
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
                report = fleet.upload(path, functools.partial(_advance, progress, task))
            except ServiceError as exc:
                if exc.status == 401:
                    raise  # no file would go: one line about the token, not one per file
                failed += 1
                kept = kept_note(exc.body.get("accepted") or {})
                progress.console.print(f"Error: {path}: {exc}{kept}", style="red", markup=False, soft_wrap=True)
                continue
            finally:
                progress.remove_task(task)
            click.echo(
                f"{path}: runs {', '.join(report['runs']) or '-'}: {report['chunks_new']} new chunks "
                f"({report['bytes_new']:,} bytes), {report['chunks_duplicate']} already held"
            )
            for warning in report.get("warnings", []):
                progress.console.print(f"Warning: {path}: {warning}", style="yellow", markup=False, soft_wrap=True)
    if failed:
        raise SystemExit(1)


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
