"""`fleet runs pull|pulls`: asking a run's robot to send what only it holds, and following those
pulls; and what `fleet runs show` says of the robot's own copy."""

from __future__ import annotations

import json
from typing import Any

import click
from rich.console import Console
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console, when


@click.command("pull")
@api_option
@click.argument("run_id")
@click.option("--include", multiple=True, help="send only these entities: /a/b or /a/** (repeatable)")
@click.option("--exclude", multiple=True, help="leave these entities out (wins over --include)")
@click.option("--timeline", help="send chunks overlapping --start/--end on this timeline")
@click.option("--start", help="sequence number, duration (12.5s) or timestamp (ISO-8601 or ns)")
@click.option("--end", help="as --start; inclusive")
@click.option("--json", "as_json", is_flag=True, help="print the pull as JSON")
def runs_pull(
    api_url: str,
    run_id: str,
    include: tuple[str, ...],
    exclude: tuple[str, ...],
    timeline: str | None,
    start: str | None,
    end: str | None,
    as_json: bool,
) -> None:
    """Ask the run's robot to send (part of) the run: queued until its agent picks it up. Asking
    again for the same part while it is pending or sending answers that pull."""
    with client(api_url) as fleet:
        pull = fleet.request_pull(
            run_id, include=list(include), exclude=list(exclude), timeline=timeline, start=start, end=end
        )
    if as_json:
        click.echo(json.dumps(pull, indent=2))
        return
    click.echo(f"{pull['id']}: {pull['state']}, for robot {pull['robot_id']}'s agent ({_part(pull)})")


@click.command("pulls")
@api_option
@click.argument("run_id")
@click.option("--json", "as_json", is_flag=True, help="print JSON (the service's answer) instead of a table")
def runs_pulls(api_url: str, run_id: str, as_json: bool) -> None:
    """A run's pulls, newest first: what was asked of its robot and how far its agent got."""
    with client(api_url) as fleet:
        found = fleet.run_pulls(run_id)
    if as_json:
        click.echo(json.dumps({"pulls": found}, indent=2))
        return
    if not found:
        click.echo(f"no pulls of {run_id}: `fleet runs pull {run_id}` asks its robot for it")
        return
    stdout_console().print(pulls_table(found))


def pulls_table(found: list[dict[str, Any]]) -> Table:
    columns = ("pull", "state", "asked", "by", "part", "chunks sent", "bytes sent", "error")
    table = Table(*columns, box=None, padding=(0, 2))
    for pull in found:
        table.add_row(
            pull["id"],
            pull["state"],
            when(pull["requested_at"]),
            pull["requested_by"],
            _part(pull),
            f"{pull['chunks_sent']:,}",
            f"{pull['bytes_sent']:,}",
            pull["error"] or "",
        )
    return table


def _part(pull: dict[str, Any]) -> str:
    """What of the run a pull asks for, as the options that asked it."""
    words = [f"--include {p}" for p in pull["include"]] + [f"--exclude {p}" for p in pull["exclude"]]
    if pull["timeline"]:
        words.append(f"{pull['timeline']} {pull['start'] or '…'}..{pull['end'] or '…'}")
    return " ".join(words) or "the whole run"


def print_robot_side(console: Console, run: dict[str, Any]) -> None:
    """For `fleet runs show`: what the robot reports holding of the run, and its latest pulls."""
    copy = run.get("robot_copy")
    if copy:
        console.print(
            f"robot copy on {copy['robot_id']} (reported {when(copy['reported_at'])}): "
            f"{copy['chunks']:,} chunks, {copy['bytes']:,} bytes; only on the robot: "
            f"{copy['local_only_chunks']:,} chunks, {copy['local_only_bytes']:,} bytes"
            + (f" ({', '.join(copy['local_only_entities'])})" if copy["local_only_entities"] else "")
            + f"; keeps it until {when(copy['keeps_until'])}",
            markup=False,
        )
    if run.get("pulls"):
        console.print("pulls (latest first):", markup=False)
        console.print(pulls_table(run["pulls"]))
