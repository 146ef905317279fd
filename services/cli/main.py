"""`fleet`: the command line of the fleet telemetry depot."""

from __future__ import annotations

import click

from services import __version__
from services.cli.rrd import rrd
from services.cli.serve import serve


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="fleet")
def cli() -> None:
    """Fleet telemetry depot for robots that log with Rerun."""


cli.add_command(serve)
cli.add_command(rrd)


def main() -> None:
    cli()
