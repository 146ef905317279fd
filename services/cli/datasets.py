"""`fleet datasets create|ls|show`: dataset snapshots (over REST).

`--event KIND` means one of two things, by whether a window is asked for: with `--before` or
`--after`, the episodes are windows around each event of these kinds (`--event intervention
--before 5 --after 2`); without, it filters the runs as `fleet runs ls --event` does (runs with an
event of each kind), one episode per run. `--window-event KIND` always names the window's events.
"""

from __future__ import annotations

import json
from typing import Any

import click
from rich.table import Table

from services.cli import dataset_exports
from services.cli.client import api_option, client
from services.cli.output import stdout_console
from services.cli.runs import run_filters


@click.group()
def datasets() -> None:
    """Dataset snapshots: a selection of runs (and windows around events) kept as immutable versions."""


@datasets.command("create")
@api_option
@click.argument("name")
@run_filters
@click.option(
    "--event",
    multiple=True,
    help="with --before/--after: a window around each event of this kind (repeatable); "
    "without: runs with an event of this kind, as `fleet runs ls --event`",
)
@click.option("--window-event", multiple=True, help="a window around each event of this kind (repeatable)")
@click.option("--before", type=float, help="seconds before each event's start (steps on a sequence timeline)")
@click.option("--after", type=float, help="seconds after each event's end")
@click.option("--include", multiple=True, help="entities the episodes read: /a/b or /a/** (default: every one)")
@click.option("--exclude", multiple=True, help="entities left out (wins over --include)")
@click.option("--timeline", default="log_time", show_default=True, help="the timeline an export samples on")
@click.option("--fps", type=float, help="the rate an export samples at (frames per second)")
@click.option("--split", "split_text", help="split by run, e.g. train=0.9,val=0.1")
@click.option("--seed", type=int, default=0, show_default=True, help="the split's seed")
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer")
def create(api_url: str, name: str, as_json: bool, **options: Any) -> None:
    """Resolve a selection into the next version of snapshot NAME (NAME@1, NAME@2, ...)."""
    body = selection_body(**options)
    with client(api_url) as fleet:
        made = fleet.create_dataset(name, **body)
    if as_json:
        click.echo(json.dumps(made, indent=2))
        return
    click.echo(
        f"{made['ref']}: {made['episodes']:,} episodes from {made['runs']:,} runs, {made['chunks']:,} chunks, "
        f"{made['bytes'] / 1e6:,.1f} MB (rules v{made['rules_version'] or '-'})"
    )
    for split, counts in made["splits"].items():
        click.echo(f"  {split}: {counts['runs']:,} runs, {counts['episodes']:,} episodes")
    for skipped in made["skipped"]:
        click.echo(f"  skipped {skipped['run']}: {skipped['why']}")


def selection_body(
    *,
    robot: tuple[str, ...] = (),
    application: tuple[str, ...] = (),
    since: str | None = None,
    until: str | None = None,
    status: str | None = None,
    tier: str | None = None,
    entity: tuple[str, ...] = (),
    prop: tuple[str, ...] = (),
    metric: tuple[str, ...] = (),
    tag: tuple[str, ...] = (),
    event: tuple[str, ...] = (),
    window_event: tuple[str, ...] = (),
    before: float | None = None,
    after: float | None = None,
    include: tuple[str, ...] = (),
    exclude: tuple[str, ...] = (),
    timeline: str = "log_time",
    fps: float | None = None,
    split_text: str | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """The request body of `fleet datasets create`'s options (see the module's note on --event)."""
    windowed = before is not None or after is not None or bool(window_event)
    kinds = [*window_event, *(event if before is not None or after is not None else ())]
    if windowed and not kinds:
        raise click.UsageError("--before/--after put windows around events: name their kind with --event KIND")
    from services.datasets.selection import parse_split  # the service's parsers load only when used
    from services.runs.service import parse_properties

    body: dict[str, Any] = {
        "robot": list(robot),
        "application": list(application),
        "since": since,
        "until": until,
        "status": status,
        "tier": tier,
        "entity": list(entity),
        "properties": parse_properties(list(prop)),
        "metric": list(metric),
        "tag": list(tag),
        "event": [] if before is not None or after is not None else list(event),
        "include": list(include) or None,
        "exclude": list(exclude),
        "timeline": timeline,
        "fps": fps,
        "split": dict(parse_split(split_text)) if split_text else None,
        "seed": seed,
    }
    if windowed:
        body["event_window"] = {"event": list(dict.fromkeys(kinds)), "before_s": before or 0, "after_s": after or 0}
    return body


@datasets.command("ls")
@api_option
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer")
def ls(api_url: str, as_json: bool) -> None:
    """Snapshots, each with its latest version."""
    with client(api_url) as fleet:
        found = fleet.datasets()
    if as_json:
        click.echo(json.dumps(found, indent=2))
        return
    table = Table("dataset", "latest", "episodes", "runs", "chunks", "MB", "by", "at", box=None, padding=(0, 2))
    for d in found:
        v = d["latest"] or {}
        table.add_row(
            d["name"],
            v.get("ref", "-"),
            f"{v.get('episodes', 0):,}",
            f"{v.get('runs', 0):,}",
            f"{v.get('chunks', 0):,}",
            f"{v.get('bytes', 0) / 1e6:,.1f}",
            v.get("created_by", "-"),
            v.get("created_at", "-"),
        )
    stdout_console().print(table)


@datasets.command("show")
@api_option
@click.argument("ref")
@click.option("--limit", type=int, default=100, show_default=True, help="episodes shown")
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer")
def show(api_url: str, ref: str, limit: int, as_json: bool) -> None:
    """NAME: its versions; NAME@N: that version's selection and episodes."""
    from services.datasets.service import parse_ref

    name, number = parse_ref(ref)
    with client(api_url) as fleet:
        answer = fleet.dataset(name) if number is None else fleet.dataset_version(name, number, limit=limit)
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    console = stdout_console()
    if number is None:
        table = Table("version", "episodes", "runs", "chunks", "MB", "rules", "by", "at", box=None, padding=(0, 2))
        for v in answer["versions"]:
            table.add_row(
                v["ref"],
                f"{v['episodes']:,}",
                f"{v['runs']:,}",
                f"{v['chunks']:,}",
                f"{v['bytes'] / 1e6:,.1f}",
                str(v["rules_version"] or "-"),
                v["created_by"],
                v["created_at"],
            )
        console.print(table)
        return
    console.print(
        f"[bold]{answer['ref']}[/bold]  by {answer['created_by']} at {answer['created_at']}  "
        f"{answer['episodes']:,} episodes, {answer['runs']:,} runs, {answer['chunks']:,} chunks",
        markup=True,
    )
    console.print("selection: " + json.dumps(answer["selection"], sort_keys=True), markup=False)
    table = Table(
        "#", "run", "robot", "split", "timeline", "start", "end", "chunks", "missing", box=None, padding=(0, 2)
    )
    for e in answer["episodes_page"]:
        table.add_row(
            str(e["index"]),
            e["run_id"],
            e["robot_id"],
            e["split"] or "-",
            e["timeline"],
            "-" if e["start"] is None else str(e["start"]),
            "-" if e["end"] is None else str(e["end"]),
            f"{e['chunks']:,}",
            e["missing_why"] if e["missing"] else "",
        )
    console.print(table)
    for skipped in answer["skipped"]:
        console.print(f"skipped {skipped['run']}: {skipped['why']}", markup=False)
    if answer["next_cursor"]:
        click.echo(f"(more: --json, or GET /v1/datasets/{name}/{number}?cursor={answer['next_cursor']})")


datasets.add_command(dataset_exports.export)
datasets.add_command(dataset_exports.exports)
datasets.add_command(dataset_exports.export_cancel)
