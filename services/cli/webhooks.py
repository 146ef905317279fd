"""`fleet webhooks add|ls|rm|deliveries`: endpoints told of events, sealed runs and silent robots by
a signed POST (an admin's work, over REST). A new webhook's signing secret is printed once, alone
on stdout, so `SECRET=$(fleet webhooks add ...)` keeps it; nothing else ever shows it again."""

from __future__ import annotations

import json

import click
from rich.table import Table
from rich.text import Text

from services.cli.client import api_option, client
from services.cli.output import stdout_console, when


@click.group()
def webhooks() -> None:
    """Webhooks (admin): a signed JSON POST to a URL for each occurrence it is told of. The depot
    sends only to hosts its FLEET_WEBHOOK_HOSTS lists."""


@webhooks.command("add")
@api_option
@click.argument("url")
@click.option(
    "--on",
    "on",
    multiple=True,
    required=True,
    help="what it is told of (repeatable): event:KIND (e.g. event:intervention), event:* (every event), "
    "run.sealed, robot.silent (a live run sent nothing for FLEET_SILENT_AFTER_S)",
)
@click.option(
    "--format",
    "body_format",
    type=click.Choice(["json", "slack"]),
    default="json",
    show_default=True,
    help='json: the occurrence as a JSON document; slack: a Slack-compatible {"text": ...} message',
)
def add(api_url: str, url: str, on: tuple[str, ...], body_format: str) -> None:
    """Add a webhook and print its signing secret, once, alone on stdout (a summary goes to stderr):
    each POST carries X-Fleet-Signature: sha256=HMAC-SHA256(secret, body). Example:

        fleet webhooks add https://hooks.example/fleet --on event:intervention --on robot.silent"""
    with client(api_url) as fleet:
        answer = fleet.add_webhook(url, list(on), body_format)
    click.echo(answer["secret"])
    click.echo(
        f"webhook {answer['id']} to {answer['url']}: on {' '.join(answer['on'])}, format {answer['format']}; "
        "its signing secret is shown once: store it now",
        err=True,
    )


@webhooks.command("ls")
@api_option
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer instead of a table")
def ls(api_url: str, as_json: bool) -> None:
    """List webhooks: where each goes and what it is told of (never its secret)."""
    with client(api_url) as fleet:
        answer = fleet.webhooks()
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    table = Table("id", "url", "on", "format", "created", "by", box=None, padding=(0, 2))
    for hook in answer["webhooks"]:
        cells = (
            hook["id"],
            hook["url"],
            " ".join(hook["on"]),
            hook["format"],
            when(hook["created_at"]),
            hook["created_by"],
        )
        table.add_row(*(Text(c) for c in cells))  # URLs and names are anyone's text: no markup read in them
    stdout_console().print(table)


@webhooks.command("rm")
@api_option
@click.argument("webhook_id")
def rm(api_url: str, webhook_id: str) -> None:
    """Remove a webhook (its id from `fleet webhooks ls`); its pending deliveries are not sent."""
    with client(api_url) as fleet:
        answer = fleet.remove_webhook(webhook_id)
    click.echo(f"{answer['id']} ({answer['url']}): removed")


@webhooks.command("deliveries")
@api_option
@click.argument("webhook_id")
@click.option("--limit", type=click.IntRange(1, 1000), default=50, show_default=True, help="deliveries shown")
@click.option("--cursor", help="where the previous page ended (printed after it)")
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer instead of a table")
def deliveries(api_url: str, webhook_id: str, limit: int, cursor: str | None, as_json: bool) -> None:
    """A webhook's deliveries, newest first: each one's state, attempts, and its last answer or error."""
    with client(api_url) as fleet:
        answer = fleet.webhook_deliveries(webhook_id, limit, cursor)
    if as_json:
        click.echo(json.dumps(answer, indent=2))
        return
    table = Table("delivery", "occurrence", "state", "attempts", "last", "created", "delivered / next", box=None)
    for d in answer["deliveries"]:
        last = " ".join(str(x) for x in (d["last_status"], d["last_error"]) if x is not None) or "-"
        moment = d["delivered_at"] or d["next_at"]
        cells = (
            d["id"],
            d["occurrence"],
            d["state"],
            str(d["attempts"]),
            last,
            when(d["created_at"]),
            when(moment) if moment else "-",
        )
        table.add_row(*(Text(c) for c in cells))
    stdout_console().print(table)
    if answer["next_cursor"]:
        click.echo(f"more: fleet webhooks deliveries {webhook_id} --cursor {answer['next_cursor']}", err=True)
