"""`fleet tokens create|ls|revoke`: the depot's tokens (an admin's work, over REST). A new token is
printed once, alone on stdout, so `TOKEN=$(fleet tokens create ...)` keeps it; nothing else ever
shows it again."""

from __future__ import annotations

import datetime as dt
import json

import click
from rich.table import Table
from rich.text import Text

from services.auth.scopes import Scope
from services.cli.client import Duration, api_option, client
from services.cli.output import stdout_console, when


@click.group()
def tokens() -> None:
    """Tokens for robots, people and Rerun clients (admin). A command finds its own token in
    FLEET_TOKEN, else in $FLEET_DATA_DIR/admin.token on the service's machine."""


@tokens.command("create")
@api_option
@click.option(
    "--scope",
    "scopes",
    multiple=True,
    required=True,
    type=click.Choice([s.value for s in Scope], case_sensitive=False),
    help="what it may do (repeatable): ingest (one robot's runs: give --robot), read (list, download, "
    "SQL), write (upload, pin, restore, promote; implies read), admin (delete, retention, tokens; implies all)",
)
@click.option("--robot", help="the robot an ingest token writes runs for")
@click.option("--name", help="who acts with it (the actor in events and tombstones) [default: the robot id]")
@click.option("--expires", type=Duration(), help="lifetime: 90d, 12h, 30m, 45s, 2w [default: never]")
@click.option(
    "--host",
    "hosts",
    multiple=True,
    help="a host name Rerun's viewer and SDK may send it to (allowed_hosts; repeatable) "
    "[default: the service's FLEET_PUBLIC_HOSTS, else its own names]",
)
def create(
    api_url: str,
    scopes: tuple[str, ...],
    robot: str | None,
    name: str | None,
    expires: dt.timedelta | None,
    hosts: tuple[str, ...],
) -> None:
    """Create a token and print it, once, alone on stdout (a summary goes to stderr): store it now,
    nothing shows it again. Examples:

        fleet tokens create --scope read --name alice --expires 90d

        fleet tokens create --scope ingest --robot robot-7"""
    with client(api_url) as fleet:
        answer = fleet.create_token(
            [s.lower() for s in scopes],
            robot=robot,
            name=name,
            expires_in_s=expires.total_seconds() if expires else None,
            hosts=list(hosts),
        )
    click.echo(answer["token"])
    click.echo(
        f"token {answer['id']} for {answer['subject']}: scopes {' '.join(answer['scopes'])}, "
        f"robot {answer['robot'] or '-'}, expires {when(answer['expires_at']) if answer['expires_at'] else 'never'}, "
        f"allowed hosts {', '.join(answer.get('allowed_hosts') or []) or '-'}; shown once: store it now",
        err=True,
    )


@tokens.command("ls")
@api_option
@click.option("--all", "include_revoked", is_flag=True, help="also revoked tokens")
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer instead of a table")
def ls(api_url: str, include_revoked: bool, as_json: bool) -> None:
    """List tokens: who each is for and what it grants (never the token itself)."""
    with client(api_url) as fleet:
        answer = fleet.tokens(include_revoked)
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    table = Table("id", "name", "subject", "scopes", "robot", "created", "expires", "revoked", box=None, padding=(0, 2))
    for t in answer["tokens"]:
        cells = (
            t["id"],
            t["name"],
            t["subject"],
            " ".join(t["scopes"]),
            t["robot"] or "-",
            when(t["created_at"]),
            when(t["expires_at"]) if t["expires_at"] else "never",
            f"{when(t['revoked_at'])} by {t['revoked_by']}" if t["revoked_at"] else "-",
        )
        table.add_row(*(Text(c) for c in cells))  # names are anyone's text: no markup read in them
    stdout_console().print(table)


@tokens.command("revoke")
@api_option
@click.argument("token_id")
def revoke(api_url: str, token_id: str) -> None:
    """Revoke a token (its id from `fleet tokens ls`): it and the links it signed are refused from
    now on (by every node of the service within its FLEET_AUTH_CACHE_S)."""
    with client(api_url) as fleet:
        answer = fleet.revoke_token(token_id)
    click.echo(f"{answer['id']} ({answer['name']}): revoked at {when(answer['revoked_at'])} by {answer['revoked_by']}")
