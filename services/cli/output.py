"""Consoles for the CLI: tables never cut ids short when the output goes to a pipe or a file; byte
transfers show one kind of progress bar, on stderr."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

PIPE_WIDTH = 200


def stdout_console() -> Console:
    return Console() if sys.stdout.isatty() else Console(width=PIPE_WIDTH)


def transfer_progress(console: Console | None = None, *, disable: bool = False) -> Progress:
    """A progress bar of bytes moved (size and speed), gone once done."""
    return Progress(
        "{task.description}",
        BarColumn(),
        DownloadColumn(),
        TransferSpeedColumn(),
        console=console or Console(stderr=True),
        transient=True,
        disable=disable,
    )


def when(iso: str | None) -> str:
    """A time from the service (ISO-8601 UTC) to the second, as people read it; "-" for none."""
    import datetime as dt

    if not iso:
        return "-"
    try:
        return dt.datetime.fromisoformat(iso).astimezone(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    except ValueError:
        return iso
