"""`fleet events ls|view|pull`, and `fleet runs annotate|tag|untag`: the events and tags of runs,
and where an event's window is (over REST)."""

from __future__ import annotations

import json
import shlex
import subprocess
from typing import Any

import click
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console, timeline_value, when
from services.cli.runs import _as_typed, find_rerun

SEVERITIES = ("info", "warn", "error")


@click.group()
def events() -> None:
    """Events on runs: made by rules, by robots, by people."""


@events.command("ls")
@api_option
@click.option("--kind", multiple=True, help="event kind (repeatable)")
@click.option("--robot", multiple=True, help="robot id (repeatable)")
@click.option("--run", multiple=True, help="run id (repeatable)")
@click.option("--severity", multiple=True, type=click.Choice(SEVERITIES))
@click.option("--since", help="recorded by the depot at or after (ISO-8601)")
@click.option("--until", help="recorded by the depot before (ISO-8601)")
@click.option("--source", help="`rule NAME@VERSION`, a person's name, or `robot`")
@click.option("--pending", is_flag=True, help="only events whose window is asked of the robot, not at the depot yet")
@click.option("--limit", type=int, default=100, show_default=True)
@click.option("--cursor", help="`next_cursor` of the previous page")
@click.option("--json", "as_json", is_flag=True, help="print JSON (the service's answer) instead of a table")
def events_ls(api_url: str, as_json: bool, **filters: Any) -> None:
    """List events, newest first."""
    filters["pending"] = filters["pending"] or None  # asked only when given
    with client(api_url) as fleet:
        page = fleet.events(**{k: list(v) if isinstance(v, tuple) else v for k, v in filters.items()})
    if as_json:
        click.echo(json.dumps(page, indent=2))
        return
    table = Table("event", "run", "robot", "kind", "severity", "timeline", "start", "end", "source", "label", "data")
    table.box, table.padding = None, (0, 2)
    for e in page["events"]:
        table.add_row(
            e["id"],
            e["run_id"],
            e["robot_id"],
            e["kind"],
            e["severity"],
            e["timeline"],
            timeline_value(e["timeline_type"], e["start"]),
            timeline_value(e["timeline_type"], e["end"]),
            e["source"],
            e["label"],
            e["data"]["state"] if e.get("data") else "",
        )
    stdout_console().print(table)
    if page["next_cursor"]:
        click.echo(f"(more: --cursor {page['next_cursor']})")


@events.command("view")
@api_option
@click.argument("event_id")
@click.option("--open", "open_viewer", is_flag=True, help="run the command instead of printing it")
@click.option("--json", "as_json", is_flag=True, help="print the event (the service's answer) instead")
def events_view(api_url: str, event_id: str, open_viewer: bool, as_json: bool) -> None:
    """Print the `rerun` command that opens the event's window of its run (a few seconds either
    side) in the viewer; with auth on its URL is a signed link, which expires."""
    with client(api_url) as fleet:
        event = fleet.event(event_id)
    if as_json:
        click.echo(json.dumps(event, indent=2))
        return
    click.echo(
        f"{event['kind']} ({event['severity']}) on {event['run_id']}, {event['timeline']} "
        f"{timeline_value(event['timeline_type'], event['start'])} to "
        f"{timeline_value(event['timeline_type'], event['end'])}: {event['label']}",
        err=True,
    )
    rerun = find_rerun()
    if not open_viewer:
        click.echo(shlex.join([_as_typed(rerun), event["viewer_url"]]))
        return
    if rerun is None:
        raise click.ClickException("the Rerun viewer is not installed: pip install rerun-sdk")
    raise SystemExit(subprocess.call([rerun, event["viewer_url"]]))


@events.command("pull")
@api_option
@click.argument("event_id")
@click.option("--json", "as_json", is_flag=True, help="print the pull (the service's answer)")
def events_pull(api_url: str, event_id: str, as_json: bool) -> None:
    """Ask the robot for the window of an event a trigger pulled (one held on the robot over its
    budget, or that failed): queued until its agent picks it up; a pull of the event still pending or
    sending is answered instead."""
    with client(api_url) as fleet:
        pull = fleet.pull_event(event_id)
    if as_json:
        click.echo(json.dumps(pull, indent=2))
        return
    window = f"{pull['timeline']} {pull['start']}..{pull['end']}" if pull["timeline"] else "the whole run"
    click.echo(f"{pull['id']}: {pull['state']}, for robot {pull['robot_id']}'s agent ({window} of {pull['run_id']})")


@click.command("annotate")
@api_option
@click.argument("run_id")
@click.option("--timeline", default="log_time", show_default=True, help="one of the run's timelines")
@click.option("--start", required=True, help="ISO-8601 or ns (timestamp), an integer (sequence), 12.5s (duration)")
@click.option("--end", help="as --start [default: --start, an instant]")
@click.option("--label", default="", help="what happened")
@click.option("--note", default="", help="more about it")
@click.option("--severity", type=click.Choice(SEVERITIES), default="info", show_default=True)
@click.option("--kind", help="the event's kind [default: annotation]")
@click.option("--json", "as_json", is_flag=True, help="print the event (the service's answer)")
def runs_annotate(api_url: str, run_id: str, timeline: str, start: str, as_json: bool, **fields: Any) -> None:
    """Mark a time range of a run as an event of yours."""
    with client(api_url) as fleet:
        event = fleet.annotate(run_id, timeline, start, **fields)
    if as_json:
        click.echo(json.dumps(event, indent=2))
        return
    click.echo(f"{event['id']}: {event['kind']} on {run_id} by {event['source']}")


@click.command("tag")
@api_option
@click.argument("run_id")
@click.argument("tags", nargs=-1, required=True)
def runs_tag(api_url: str, run_id: str, tags: tuple[str, ...]) -> None:
    """Tag a run (TAG: no whitespace or comma, at most 128 characters)."""
    with client(api_url) as fleet:
        answer = fleet.tag(run_id, list(tags))
    _print_tags(answer)


@click.command("untag")
@api_option
@click.argument("run_id")
@click.argument("tags", nargs=-1, required=True)
def runs_untag(api_url: str, run_id: str, tags: tuple[str, ...]) -> None:
    """Remove tags from a run."""
    with client(api_url) as fleet:
        answer = fleet.untag(run_id, list(tags))
    _print_tags(answer)


def _print_tags(answer: dict[str, Any]) -> None:
    if not answer["tags"]:
        click.echo(f"{answer['run']}: no tags")
    for t in answer["tags"]:
        click.echo(f"{answer['run']}  {t['tag']}  added by {t['added_by']} at {when(t['added_at'])}")
