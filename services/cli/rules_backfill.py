"""`fleet rules backfill`: every stored run evaluated under the running rules now, over REST."""

from __future__ import annotations

import click

from services.cli.client import api_option, client
from services.cli.retention import _follow


@click.command("backfill")
@api_option
def backfill(api_url: str) -> None:
    """Evaluate every stored run the running rules have not (a rules change, runs sealed while the
    evaluation failed, cold runs restored since), with a line per run; re-runnable, and resumable
    after a kill (runs already at the running version are not read again). Cold runs are skipped:
    restore them to evaluate them. Exit status 1 if any run failed."""
    with client(api_url) as fleet:
        end = _follow(fleet.rules_backfill(), "backfill")
    if end.get("event") in ("error", "busy"):
        raise click.ClickException(str(end.get("detail")))
    click.echo(
        f"{end.get('evaluated', 0)} runs evaluated, {end.get('skipped_cold', 0)} skipped (cold), "
        f"{end.get('skipped', 0)} skipped (hot on another node), {end.get('failed', 0)} failed; "
        f"{end.get('bytes_read', 0) / 1e6:,.1f} MB read"
    )
    if end.get("failed"):
        raise SystemExit(1)
