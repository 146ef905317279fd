"""`fleet agent`: run the robot's agent; `fleet agent status`: where its runs stand.

The agent's flags are made from its `AgentSettings`, as `fleet serve`'s are from the depot's
`Settings`: its own `agent_*` settings without the prefix (`--spool`, `--listen`, `--depot`, ...)
and the ingest settings it shares with the depot (`--max-message-size`, ...); each also a FLEET_*
variable or a key of the TOML file named by FLEET_CONFIG; the token also FLEET_TOKEN, the depot's
REST address also FLEET_API_URL."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from services.cli.settings_options import SettingsCommand

if TYPE_CHECKING:
    from services.agent.settings import AgentSettings

# Settings that are no option of `fleet agent`, and why (shown after the options).
NOT_OPTIONS = {"agent_bandwidth_rules": "a list of tables: TOML only"}
# Options also read from a variable of the CLI's own (as every command that talks to the depot).
ENVVARS = {"agent_token": "FLEET_TOKEN", "agent_api_url": "FLEET_API_URL"}


def _agent_settings() -> type[AgentSettings]:
    from services.agent.settings import AgentSettings

    return AgentSettings


class AgentCommand(click.Group, SettingsCommand):
    """`fleet agent` runs the agent unless a subcommand (status) is named."""

    settings_class = staticmethod(_agent_settings)
    flag_prefix = "agent_"
    not_options = NOT_OPTIONS
    envvars = ENVVARS


@click.group(cls=AgentCommand, invoke_without_command=True)
@click.pass_context
def agent(ctx: click.Context, /, **flags: object) -> None:
    """Run the robot's agent: the SDK streams to it (rr.GrpcSink("rerun+http://127.0.0.1:9876/proxy")),
    it keeps every message in its spool and forwards runs to the depot, filling any gap a cut link
    leaves. Every flag can also be set as the variable named in its help, or in a TOML file named by
    FLEET_CONFIG."""
    if ctx.invoked_subcommand is not None:
        ctx.obj = flags
        return
    import asyncio
    import logging

    from services.agent.service import run_agent
    from services.agent.settings import load_agent_settings
    from services.routine_logs import quiet_routine_requests
    from services.startup import hold_data_dir

    settings = load_agent_settings(**flags)
    held = hold_data_dir(settings.agent_spool, what="spool", command="fleet agent", fix="--spool or FLEET_AGENT_SPOOL")
    with held, contextlib.suppress(KeyboardInterrupt):  # Ctrl-C: the spool is safe, the agent stops
        _check_ports(settings)  # a refusal is the only line said, before anything starts
        logging.basicConfig(level=logging.INFO, format="%(levelname)s:     %(name)s: %(message)s")
        quiet_routine_requests()  # its pull polls and copy reports: DEBUG, not a line every 5 s
        if settings.agent_token is None:
            click.echo("fleet agent: no token (FLEET_TOKEN): a depot with auth on refuses the robot's runs", err=True)
        click.echo(
            f"fleet agent: spool {settings.agent_spool.resolve()}, SDK to rerun+http://{settings.agent_listen}/proxy, "
            f"depot {settings.agent_depot}"
        )
        asyncio.run(run_agent(settings))


def _check_ports(settings: AgentSettings) -> None:
    """Both addresses are HOST:PORT and free (InvalidArgumentError or ConflictError naming the setting)."""
    from core.errors import InvalidArgumentError
    from services.startup import is_loopback, listen, split_addr

    for setting, what in (("agent_listen", "agent's SDK"), ("agent_status_addr", "agent's status")):
        flag = setting.removeprefix("agent_").replace("_", "-")
        try:
            host, port = split_addr(getattr(settings, setting))
        except ValueError as exc:
            raise InvalidArgumentError(f"{setting}: {exc}: set it with --{flag} or FLEET_{setting.upper()}") from None
        if not is_loopback(host) and not settings.insecure:
            raise InvalidArgumentError(
                f"{setting} {host}:{port} is not a loopback address: the agent takes data with no token and sends "
                f"it on with the robot's, so anyone who reaches it could write the robot's runs; listen on "
                f"127.0.0.1 (--{flag}), or give --insecure if the network it listens on is the robot's own"
            )
        listen(host, port, what, setting).close()


@agent.command()
@click.option("--spool", type=click.Path(path_type=Path), help="The agent's spool (else as `fleet agent` reads it).")
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON.")
@click.pass_context
def status(ctx: click.Context, spool: Path | None, as_json: bool) -> None:
    """Per run: bytes on the robot, sent, not yet confirmed at the depot, kept on the robot only; the
    link and the backlog; the watched MCAP files (bags) uploaded, pending, failed. Works whether the
    agent runs or not (give the same --spool)."""
    from services.agent.settings import load_agent_settings
    from services.agent.status import status_report

    settings = load_agent_settings(**{**(ctx.obj or {}), "agent_spool": spool})
    report = status_report(settings.agent_spool)
    if as_json:
        click.echo(json.dumps(report, indent=2))
    else:
        _print(report)
    if "error" in report:
        raise SystemExit(1)


def _print(report: dict[str, Any]) -> None:
    if "error" in report:
        click.echo(f"Error: {report['error']}", err=True)
        return
    link = report["link"]
    if report["running"]:
        state = "running"
    elif report["heartbeat_age_s"] is None:
        state = "not running (never seen running on this spool)"
    else:
        state = f"not running (last seen {report['heartbeat_age_s']} s ago)"
    linked = "up" if link.get("up") else f"down ({link.get('error') or 'not connected'})"
    click.echo(f"agent: {state}; spool {Path(report['spool'])}: {report['spool_bytes']} bytes")
    click.echo(f"depot link: {linked}" + (f"; refused: {link['refused']}" if link.get("refused") else ""))
    click.echo(f"backlog: {report['backlog_bytes']} bytes not yet sent")
    for run in report["runs"]:
        where = "confirmed at the depot" if run["confirmed"] else f"{run['unconfirmed_at_depot_bytes']} B unconfirmed"
        local = f", {run['local_only_chunks']} chunks on the robot only" if run["local_only_chunks"] else ""
        click.echo(
            f"  {run['run']}: {run['local_bytes']} B local, {run['sent_bytes']} B sent, {where}"
            f"{', open' if run['open'] else ''}{local}"
        )
    rules = report.get("rules") or {}
    if rules:
        refused = (
            f"; version {rules['refused_version']} refused: {rules['refused_why']}"
            if rules.get("refused_version")
            else ""
        )
        click.echo(f"rules: version {rules.get('version', 0)}, {rules.get('triggers', 0)} triggers{refused}")
    for window in report.get("windows", []):
        why = f" ({window['error']})" if window.get("error") else ""
        click.echo(
            f"  trigger window {window['window']} of {window['run']} ({window['event']}): {window['state']}, "
            f"{window['bytes_sent']} B sent{why}"
        )
    bags = report.get("bags") or {}
    if any(bags.get(k) for k in ("pending", "uploaded", "failed")):
        now = f"; uploading {bags['uploading']}" if bags.get("uploading") else ""
        why = f"; {bags['error']}" if bags.get("error") else ""
        click.echo(f"bags: {bags['pending']} pending, {bags['uploaded']} uploaded, {bags['failed']} failed{now}{why}")
        for failure in bags.get("failures", []):
            click.echo(f"  failed {failure['path']} (run {failure['run']}): {failure['error']}")
