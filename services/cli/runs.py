"""`fleet runs ls|show` (and `pull|pulls`, from `pulls.py`), `fleet download`, `fleet view`: finding
runs and opening them (over REST)."""

from __future__ import annotations

import datetime as dt
import functools
import json
import os
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
from rich.console import Console
from rich.progress import Progress, TaskID
from rich.table import Table

from core.states import RestoreState, RunStatus, Tier
from services.cli.client import Duration, api_option, client
from services.cli.output import property_value, stdout_console, timeline_value, transfer_progress, when
from services.cli.pulls import print_robot_side, runs_pull, runs_pulls


def _entity_options(func: Any) -> Any:
    func = click.option("--include", multiple=True, help="keep only these entities: /a/b or /a/** (repeatable)")(func)
    func = click.option("--exclude", multiple=True, help="drop these entities (wins over --include)")(func)
    func = click.option("--timeline", help="keep chunks overlapping --start/--end on this timeline")(func)
    func = click.option("--start", help="sequence number, duration (12.5s) or timestamp (ISO-8601 or ns)")(func)
    func = click.option("--end", help="as --start; inclusive")(func)
    func = click.option("--no-latest-at", is_flag=True, help="leave out the data from before --start")(func)
    func = click.option("--exact", is_flag=True, help="cut chunks to the rows inside the window")(func)
    return click.option("--no-blueprint", is_flag=True, help="leave the run's blueprint out")(func)


def _recording_params(
    include: tuple[str, ...],
    exclude: tuple[str, ...],
    no_blueprint: bool,
    timeline: str | None,
    start: str | None,
    end: str | None,
    no_latest_at: bool,
    exact: bool,
) -> dict[str, Any]:
    return {
        "include": list(include),
        "exclude": list(exclude),
        "blueprint": "false" if no_blueprint else None,
        "timeline": timeline,
        "start": start,
        "end": end,
        "latest_at": "false" if no_latest_at else None,
        "exact": "true" if exact else None,
    }


@click.group()
def runs() -> None:
    """Find runs."""


runs.add_command(runs_pull)
runs.add_command(runs_pulls)


F = TypeVar("F", bound=Callable[..., Any])

RUN_FILTERS = (
    click.option("--robot", multiple=True, help="robot id (repeatable)"),
    click.option("--application", multiple=True, help="application id (repeatable)"),
    click.option("--since", help="runs started at or after (ISO-8601)"),
    click.option("--until", help="runs started before (ISO-8601)"),
    click.option("--status", type=click.Choice([s.value for s in RunStatus])),
    click.option("--tier", type=click.Choice([t.value for t in Tier])),
    click.option("--entity", multiple=True, help="runs that have an entity: /a/b or /a/** (repeatable)"),
    click.option("--property", "prop", multiple=True, help="NAME.FIELD=VALUE, e.g. fleet.robot_id=robot-7"),
    click.option("--metric", multiple=True, help="NAME OP VALUE, OP one of > >= < <= = != (e.g. distance_m>100)"),
    click.option("--tag", multiple=True, help="runs with this tag (repeatable: all of them)"),
)


def run_filters(command: F) -> F:
    """The run filters `fleet runs ls` and `fleet datasets create` share (each adds its own --event)."""
    for option in reversed(RUN_FILTERS):
        command = option(command)
    return command


@runs.command("ls")
@api_option
@run_filters
@click.option("--event", multiple=True, help="has at least one event of this kind (repeatable)")
@click.option("--sort", default="-started_at", show_default=True, help="-started_at, bytes, id, metric.NAME, ...")
@click.option("--limit", type=int, default=100, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print JSON (the service's answer) instead of a table")
def runs_ls(api_url: str, as_json: bool, prop: tuple[str, ...], **filters: Any) -> None:
    """List runs, newest first."""
    with client(api_url) as fleet:
        page = fleet.runs(
            property=list(prop), **{k: list(v) if isinstance(v, tuple) else v for k, v in filters.items()}
        )
    if as_json:
        click.echo(json.dumps(page, indent=2))
        return
    table = Table("run", "robot", "application", "started", "status", "tier", "chunks", "MB", box=None, padding=(0, 2))
    for run in page["runs"]:
        table.add_row(
            run["id"],
            run["robot_id"],
            run["application_id"],
            run["started_at"] or "-",
            run["status"],
            run["tier"],
            f"{run['chunks']:,}",
            f"{run['bytes'] / 1e6:,.1f}",
        )
    stdout_console().print(table)
    if page["next_cursor"]:
        click.echo(f"(more: --limit, or GET /v1/runs?cursor={page['next_cursor']})")


@runs.command("show")
@api_option
@click.argument("run_id")
@click.option("--json", "as_json", is_flag=True)
def runs_show(api_url: str, run_id: str, as_json: bool) -> None:
    """One run: metadata, entities, timelines."""
    with client(api_url) as fleet:
        run = fleet.run(run_id)
    if as_json:
        click.echo(json.dumps(run, indent=2))
        return
    console = stdout_console()
    console.print(
        f"[bold]{run['id']}[/bold]  robot {run['robot_id']}  application {run['application_id']}  "
        f"{run['status']}, {run['tier']}  SDK {run['sdk_version']}  {run['chunks']:,} chunks, "
        f"{run['bytes']:,} bytes"
    )
    console.print(
        f"started {when(run['started_at'])}  ended {when(run.get('ended_at'))}  "
        f"last data {when(run.get('last_data_at'))}",
        markup=False,
    )
    for name, fields in sorted(run["properties"].items()):
        values = fields.items() if isinstance(fields, dict) else [("", fields)]
        shown = ", ".join(f"{key}={property_value(key, value)}" if key else str(value) for key, value in values)
        console.print(f"property {name}: {shown}", markup=False)
    entities = Table("entity", "chunks", "rows", "bytes", "archetypes", box=None, padding=(0, 2))
    for e in run["entities"]:
        entities.add_row(
            e["path"],
            f"{e['chunks']:,}",
            f"{e['rows']:,}",
            f"{e['bytes']:,}",
            ", ".join(a.rsplit(".", 1)[-1] for a in e["archetypes"]),
        )
    console.print(entities)
    timelines = Table("timeline", "type", "min", "max", box=None, padding=(0, 2))
    for t in run["timelines"]:
        timelines.add_row(
            t["name"], t["type"], _timeline_value(t["type"], t["min"]), _timeline_value(t["type"], t["max"])
        )
    console.print(timelines)
    _print_corpus(console, run)
    print_robot_side(console, run)


def _print_corpus(console: Console, run: dict[str, Any]) -> None:
    """The run's metrics (and the rules version that made them), tags and events by kind."""
    metrics = run.get("metrics") or {}
    if metrics:
        shown = ", ".join(f"{name}={value}" for name, value in sorted(metrics.items()))
        console.print(f"metrics (rules v{run.get('metrics_rules_version')}): {shown}", markup=False)
    tags = run.get("tags") or []
    if tags:
        console.print("tags: " + ", ".join(f"{t['tag']} ({t['added_by']})" for t in tags), markup=False)
    counts = run.get("event_counts") or {}
    if counts:
        console.print("events: " + ", ".join(f"{kind} {n}" for kind, n in sorted(counts.items())), markup=False)
    evaluation = run.get("evaluation")
    if evaluation and (evaluation["events_capped"] or evaluation["note"]):
        console.print(f"evaluation: {evaluation['state']}: {evaluation['note'] or 'events capped'}", markup=False)


def _timeline_value(timeline_type: str, value: int | None) -> str:
    """Timestamps as dates, durations in seconds, sequences as numbers: each in the form that
    `fleet view --start/--end` accepts for that timeline."""
    return timeline_value(timeline_type, value)


@runs.command("pin")
@api_option
@click.argument("run_id")
@click.option("--unpin", is_flag=True, help="let the run's retention policy apply again")
def runs_pin(api_url: str, run_id: str, unpin: bool) -> None:
    """Pin a run: retention never deletes it (it may still be archived to cold)."""
    with client(api_url) as fleet:
        answer = fleet.pin(run_id, not unpin)
    click.echo(f"{run_id}: {'pinned' if answer['pinned'] else 'unpinned'} by {answer['by']}")


@runs.command("restore")
@api_option
@click.argument("run_id")
@click.option("--wait", is_flag=True, help="wait until the run can be downloaded")
@click.option("--timeout", type=float, default=3600.0, show_default=True, help="with --wait, give up after seconds")
def runs_restore(api_url: str, run_id: str, wait: bool, timeout: float) -> None:
    """Make a cold (archived) run downloadable again for the service's restore_days."""
    import time

    with client(api_url) as fleet:
        answer = fleet.restore(run_id)
        deadline = time.monotonic() + timeout
        with Console(stderr=True).status(f"restoring {run_id}") if wait else _nothing():
            while wait and answer.get("restore_state") != RestoreState.RESTORED:
                if time.monotonic() > deadline:
                    raise click.ClickException(f"{run_id} is still restoring after {timeout:g}s; check again later")
                time.sleep(2)  # polling the service: a restore takes minutes to hours
                life = fleet.run(run_id).get("lifecycle") or {}
                answer = {**answer, "restore_state": life.get("restore_state")}
    click.echo(f"{run_id}: {answer['restore_state']}, readable until {answer.get('restore_until')}")


def _nothing() -> Any:
    import contextlib

    return contextlib.nullcontext()


@runs.command("promote")
@api_option
@click.argument("run_id")
def runs_promote(api_url: str, run_id: str) -> None:
    """Seal a closed hot run into the warm tier now, whatever its idle time."""
    with client(api_url) as fleet, Console(stderr=True).status(f"sealing {run_id}"):
        answer = fleet.promote(run_id)
    click.echo(f"{run_id}: {answer['tier']}: {answer['detail']}")


@runs.command("rm")
@api_option
@click.argument("run_id")
@click.option("--yes", is_flag=True, help="do not ask for confirmation")
@click.option("--force", is_flag=True, help="even a run a dataset snapshot uses (its episodes then answer missing)")
def runs_rm(api_url: str, run_id: str, yes: bool, force: bool) -> None:
    """Delete a sealed run now: its objects first, then the run is marked deleted (a tombstone stays).
    A run a dataset snapshot uses is refused, naming the snapshots, unless --force."""
    if not yes:
        click.confirm(f"delete run {run_id} and all its data?", abort=True)
    with client(api_url) as fleet:
        answer = fleet.delete_run(run_id, force=force)
    click.echo(f"{run_id}: {answer['detail']}")


@click.command()
@api_option
@click.argument("run_id")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), help="file to write [RUN.rrd]")
@_entity_options
def download(api_url: str, run_id: str, output: Path | None, **filters: Any) -> None:
    """Download a run (or the entities you pick) as an .rrd file (with auth on, a `read` token)."""
    output = output or Path(f"{run_id}.rrd")
    with (
        client(api_url) as fleet,
        transfer_progress() as progress,
    ):
        task = progress.add_task(run_id, total=None)
        written = fleet.download(
            run_id, output, functools.partial(_advance, progress, task), _warn, **_recording_params(**filters)
        )
    click.echo(f"{output}: {written:,} bytes")


def _warn(warning: str) -> None:
    click.echo(f"warning: {warning}", err=True)


def _advance(progress: Progress, task: TaskID, count: int) -> None:
    progress.update(task, advance=count)


@click.command()
@api_option
@click.argument("run_id")
@_entity_options
@click.option("--open", "open_viewer", is_flag=True, help="run the command instead of printing it")
@click.option(
    "--expires",
    type=Duration(),
    help="with auth on, how long the signed link works: 30m, 12h, 7d at most [default: the service's FLEET_LINK_TTL_S]",
)
@click.option("--follow", is_flag=True, help="a live run: keep showing what it sends until it closes")
def view(
    api_url: str, run_id: str, open_viewer: bool, expires: dt.timedelta | None, follow: bool, **filters: Any
) -> None:
    """Print the `rerun` command that opens a run (or a part of it) in the viewer.

    With auth on, the URL is a signed link that expires: the viewer, a browser or a colleague
    opens it with no token, and it reads only this run with these filters; anyone holding it can
    until it expires (or until the token that asked for it is revoked). With auth off, the plain URL.
    With --follow, the viewer follows a live run over HTTP (Rerun's viewer sends no token to the
    message proxy, so with auth on this is how to watch one run live)."""
    params = _recording_params(**filters)
    if follow:
        params["follow"] = "true"
    with client(api_url) as fleet:
        # an unknown run or a bad time: one line now, not an empty viewer; a filter matching nothing: a warning
        for warning in fleet.check_recording(run_id, **params):
            _warn(warning)
        link = fleet.recording_link(run_id, expires.total_seconds() if expires else None, **params)
        url = link["url"] if link.get("expires_at") else fleet.recording_url(run_id, **params)
    if link.get("expires_at"):
        click.echo(
            f"a signed link to {run_id}, which anyone holding it can open until {when(link['expires_at'])}", err=True
        )
    rerun = find_rerun()
    if not open_viewer:
        click.echo(shlex.join([_as_typed(rerun), url]))
        return
    if rerun is None:
        raise click.ClickException("the Rerun viewer is not installed: pip install rerun-sdk")
    raise SystemExit(subprocess.call([rerun, url]))


def find_rerun() -> str | None:
    """The `rerun` installed beside this Python (the same virtualenv as `fleet`, whether or not it
    is activated), else the first one on PATH."""
    beside = Path(sys.executable).parent / "rerun"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    return shutil.which("rerun")


def _as_typed(rerun: str | None) -> str:
    """How to type the viewer's name in a shell: `rerun` when PATH finds that one (or none is
    installed here), else its full path (a virtualenv that is not activated)."""
    on_path = shutil.which("rerun")
    if rerun is None or (on_path is not None and Path(on_path).resolve() == Path(rerun).resolve()):
        return "rerun"
    return rerun
