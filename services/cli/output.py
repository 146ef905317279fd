"""Consoles for the CLI: tables never cut ids short when the output goes to a pipe or a file; byte
transfers show one kind of progress bar, on stderr; times written as the console writes them."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

from core.timefmt import property_value, timeline_value, when

__all__ = ["property_value", "stdout_console", "timeline_value", "transfer_progress", "when"]  # times: core.timefmt

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
