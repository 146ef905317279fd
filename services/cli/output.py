"""Consoles for the CLI: tables never cut ids short when the output goes to a pipe or a file."""

from __future__ import annotations

import sys

from rich.console import Console

PIPE_WIDTH = 200


def stdout_console() -> Console:
    return Console() if sys.stdout.isatty() else Console(width=PIPE_WIDTH)
