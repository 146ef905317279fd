"""`fleet rrd inspect`: what .rrd files hold, read by the depot's own RRD codec."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterator
from typing import BinaryIO

import click
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from services.cli.output import stdout_console, transfer_progress
from services.rrd.decoder import READ_SIZE, RrdDecoder
from services.rrd.footer import summarize_from_footer
from services.rrd.messages import Event
from services.rrd.summary import RrdSummary, StoreSummary, format_time, summarize


def inspect_files(files: tuple[str, ...], as_json: bool, max_message_size: int, scan: bool) -> None:
    """`fleet rrd inspect FILES`: see its help."""
    summaries = []
    for name in files or ("-",):
        try:
            if name == "-":
                summaries.append(_inspect_one("<stdin>", sys.stdin.buffer, None, max_message_size, as_json))
                continue
            summary = None if scan or not os.path.isfile(name) else summarize_from_footer(name)
            if summary is None:
                with open(name, "rb") as fh:
                    summary = _inspect_one(name, fh, os.path.getsize(name), max_message_size, as_json)
            summaries.append(summary)
        except OSError as exc:
            raise click.ClickException(f"cannot read {name}: {exc.strerror or exc}") from exc
    if as_json:
        click.echo(json.dumps([s.to_dict() for s in summaries], indent=2))
    else:
        console = stdout_console()
        for summary in summaries:
            _print_summary(console, summary)
    failed = [s for s in summaries if s.error is not None]
    for s in failed:
        click.echo(f"error: {s.source}: {s.error}", err=True)
    if failed:
        sys.exit(1)


def _read_events(
    fh: BinaryIO, summary_bytes: list[int], max_message_size: int, progress: Progress | None, task: int | None
) -> Iterator[Event]:
    decoder = RrdDecoder(max_message_size=max_message_size)
    while True:
        data = fh.read(READ_SIZE)
        if not data:
            break
        summary_bytes[0] += len(data)
        if progress is not None and task is not None:
            progress.update(task, advance=len(data))  # type: ignore[arg-type]
        yield from decoder.feed(data)
    yield from decoder.finish()


def _inspect_one(name: str, fh: BinaryIO, size: int | None, max_message_size: int, quiet: bool) -> RrdSummary:
    counted = [0]
    show = not quiet and sys.stderr.isatty() and (size or 0) > 64 * READ_SIZE
    progress = transfer_progress(disable=not show)
    with progress:
        task = progress.add_task(os.path.basename(name), total=size)
        summary = summarize(_read_events(fh, counted, max_message_size, progress, task), name)
    summary.bytes_read = counted[0]
    return summary


def _print_summary(console: Console, summary: RrdSummary) -> None:
    versions = ", ".join(sorted(set(summary.rerun_versions))) or "-"
    console.print(
        f"[bold]{summary.source}[/bold]: {summary.bytes_read:,} bytes, {summary.streams} stream(s) "
        f"(Rerun {versions}), footer: {'yes' if summary.footers else 'no'}, indexed by {summary.index}"
    )
    for store in summary.stores.values():
        _print_store(console, store)


def _print_store(console: Console, store: StoreSummary) -> None:
    sid = store.store_id
    console.print(
        f"  {sid.kind.name.lower()} [bold]{sid.recording_id}[/bold]  application {sid.application_id}"
        f"  SDK {store.sdk_version or '?'} ({store.source or '?'})  "
        f"{store.chunks:,} chunks, {store.rows:,} rows, {store.bytes:,} bytes"
    )
    if store.entities:
        table = Table("entity", "chunks", "static", "rows", "bytes", "archetypes", box=None, padding=(0, 2))
        for e in sorted(store.entities.values(), key=lambda e: e.path):
            archetypes = ", ".join(sorted(a.rsplit(".", 1)[-1] for a in e.archetypes))
            table.add_row(e.path, f"{e.chunks:,}", f"{e.static_chunks:,}", f"{e.rows:,}", f"{e.bytes:,}", archetypes)
        console.print(table)
    if store.timelines:
        table = Table("timeline", "type", "min", "max", box=None, padding=(0, 2))
        for t in sorted(store.timelines.values(), key=lambda t: t.name):
            table.add_row(t.name, t.type, format_time(t.type, t.min), format_time(t.type, t.max))
        console.print(table)
