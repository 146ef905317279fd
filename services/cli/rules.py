"""`fleet rules apply|show|history`: the rules file that makes events and metrics of runs (over
REST)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console, when


@click.group()
def rules() -> None:
    """The rules that make events and metrics of runs."""


@rules.command("apply")
@api_option
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
def rules_apply(api_url: str, file: Path) -> None:
    """Apply a rules file (TOML). A file with any problem is refused whole, each problem printed with
    its line; the running rules stay as they were."""
    from sdk_client.rest import ServiceError

    try:
        text = file.read_text()
    except UnicodeDecodeError:
        raise click.ClickException(f"{file} is not UTF-8 text") from None
    with client(api_url) as fleet:
        try:
            applied = fleet.apply_rules(text)
        except ServiceError as exc:
            problems = exc.body.get("problems")
            if exc.status != 422 or not isinstance(problems, list):
                raise
            click.echo(f"{file}: {len(problems)} problem(s), nothing was applied:", err=True)
            for problem in problems:
                click.echo(f"  {_problem(file, problem)}", err=True)
            raise SystemExit(1) from None
    if applied["changed"]:
        click.echo(f"rules version {applied['version']} applied by {applied['created_by']} ({_counts(applied)})")
    else:
        click.echo(f"unchanged: rules version {applied['version']} holds this text already")


def _problem(file: Path, problem: dict[str, Any]) -> str:
    where = f"{file}:{problem['line']}" if problem.get("line") else str(file)
    return f"{where}: {problem.get('field')}: {problem.get('message')}"


def _counts(answer: dict[str, Any]) -> str:
    held = answer["rules"]
    return f"{len(held['events'])} event rule(s), {len(held['metrics'])} metric rule(s)"


@rules.command("show")
@api_option
@click.option("--version", "version", type=int, help="an older version (see `fleet rules history`)")
@click.option("--json", "as_json", is_flag=True, help="print JSON (the service's answer)")
def rules_show(api_url: str, version: int | None, as_json: bool) -> None:
    """The running rules: version, who applied them and when, and the file's text."""
    with client(api_url) as fleet:
        answer = fleet.rules(version)
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    if answer["version"] is None:
        click.echo("no rules applied yet: `fleet rules apply FILE`")
        return
    click.echo(
        f"# rules version {answer['version']}, applied by {answer['created_by']} "
        f"at {when(answer['created_at'])} ({_counts(answer)})"
    )
    click.echo(answer["text"], nl=not answer["text"].endswith("\n"))


@rules.command("history")
@api_option
@click.option("--json", "as_json", is_flag=True, help="print JSON (the service's answer)")
def rules_history(api_url: str, as_json: bool) -> None:
    """Every version of the rules, newest first, with who applied it and when."""
    with client(api_url) as fleet:
        versions = fleet.rules_history()
    if as_json:
        click.echo(json.dumps(versions, indent=2))
        return
    table = Table("version", "applied by", "at", "digest", box=None, padding=(0, 2))
    for v in versions:
        table.add_row(str(v["version"]), v["created_by"], when(v["created_at"]), v["digest"][:12])
    stdout_console().print(table)
