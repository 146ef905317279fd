"""`fleet rrd ...`: look inside .rrd files locally (no service needed)."""

from __future__ import annotations

import click

# services.rrd.decoder.DEFAULT_MAX_MESSAGE_SIZE (a test keeps them equal), written out so that `fleet`
# does not load the RRD codec (and pyarrow) for its other commands
DEFAULT_MAX_MESSAGE_SIZE = 256 * 1024 * 1024


@click.group()
def rrd() -> None:
    """Inspect Rerun .rrd files."""


@rrd.command()
@click.argument("files", nargs=-1, type=click.Path(dir_okay=False, allow_dash=True))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document (a list, one item per file).")
@click.option(
    "--max-message-size",
    type=int,
    default=DEFAULT_MAX_MESSAGE_SIZE,
    show_default=True,
    help="Refuse messages larger than this many bytes.",
)
@click.option("--scan", is_flag=True, help="Read and check every chunk even when the file has an RRD footer (slower).")
def inspect(files: tuple[str, ...], as_json: bool, max_message_size: int, scan: bool) -> None:
    """Show what .rrd FILES hold (stdin when none or '-'): stores, application and recording ids,
    SDK version, entities with chunk and row counts, timelines with ranges.

    A file with an RRD footer is indexed from its footer (milliseconds for any size) unless --scan;
    others are read chunk by chunk. Exits 1 if any file is not valid RRD data (what was read
    before the fault is still shown)."""
    from services.cli.rrd_inspect import inspect_files

    inspect_files(files, as_json, max_message_size, scan)
