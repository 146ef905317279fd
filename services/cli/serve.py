"""`fleet serve`: run the service on the configured addresses.

Its options are made from `Settings`: one per field, named after it (`--kebab-name`), with the
field's description as help and its default shown, so that a setting is described and defaulted
in one place. An option left out is None, so the environment, the TOML file and the default apply
in that order (see `load_settings`)."""

from __future__ import annotations

import enum
import socket
import types
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Union, get_args, get_origin

import click

if TYPE_CHECKING:
    from pydantic.fields import FieldInfo

    from services.settings import Settings

AGENT = "agent_"  # the settings of `fleet agent` (its flags drop the prefix: --spool, --listen, ...)
# Settings the agent shares with the depot's ingest (the spool is its hot tier).
AGENT_SHARED = ("max_message_size", "group_commit_ms", "close_after_s", "secret_fields", "default_robot", "insecure")
# Settings that are no option of their command, and why (shown after the options).
NOT_OPTIONS = {
    "retention_policies": "a list of tables: environment or TOML only",
    "agent_bandwidth_rules": "a list of tables: TOML only",
}
# Options also read from a variable of the CLI's own (as every command that talks to the depot).
ENVVARS = {"agent_token": "FLEET_TOKEN", "agent_api_url": "FLEET_API_URL"}


def serve_setting(name: str) -> bool:
    return not name.startswith(AGENT)


def agent_setting(name: str) -> bool:
    return name.startswith(AGENT) or name in AGENT_SHARED


def settings_options(selected: Callable[[str], bool] = serve_setting) -> list[click.Option]:
    """One option per selected field of Settings but NOT_OPTIONS."""
    from services.settings import Settings

    prefix = str(Settings.model_config.get("env_prefix", ""))
    return [
        _option(name, field, prefix)
        for name, field in Settings.model_fields.items()
        if selected(name) and name not in NOT_OPTIONS
    ]


def _option(name: str, field: FieldInfo, env_prefix: str) -> click.Option:
    flag = "--" + name.removeprefix(AGENT).replace("_", "-")
    variables = " or ".join(v for v in (f"{env_prefix}{name.upper()}", ENVVARS.get(name)) if v)
    kind = _without_none(field.annotation)
    repeatable = " (repeatable)" if get_origin(kind) is list else ""
    help_text = f"{variables}: {field.description}{repeatable}{_shown_default(field)}"
    if kind is bool:
        return click.Option([f"{flag}/--no-{flag[2:]}", name], default=None, help=help_text)
    if get_origin(kind) is list:  # repeatable, and each value may itself be a comma-separated or JSON list
        return click.Option(
            [flag, name],
            type=_click_type(name, kind),
            multiple=True,
            default=None,
            callback=_list_value,
            help=help_text,
            envvar=ENVVARS.get(name),
        )
    return click.Option(
        [flag, name], type=_click_type(name, kind), default=None, help=help_text, envvar=ENVVARS.get(name)
    )


def _list_value(ctx: click.Context, param: click.Parameter, value: tuple[str, ...] | None) -> Any:
    """None when the flag is left out (the environment, the TOML file or the default apply); one
    value as given (the setting reads a comma-separated or JSON list); several as the list."""
    if not value:
        return None
    return value[0] if len(value) == 1 else list(value)


def _without_none(annotation: Any) -> Any:
    """`X` for `X | None`."""
    if get_origin(annotation) in (Union, types.UnionType):
        (annotation,) = [arg for arg in get_args(annotation) if arg is not type(None)]
    return annotation


def _click_type(name: str, kind: Any) -> click.ParamType[Any] | type:
    if kind is Path:
        return click.Path(path_type=Path)
    if isinstance(kind, type) and issubclass(kind, enum.Enum):
        return click.Choice([member.value for member in kind])
    from pydantic import SecretStr

    if kind is SecretStr:
        return str
    if kind in (str, int, float):
        return kind  # type: ignore[no-any-return]
    if get_origin(kind) is list and get_args(kind) in ((str,), (SecretStr,), (Path,)):
        return str  # the field's validator reads a comma-separated or JSON list
    raise TypeError(f"Settings.{name} ({kind}) has no option type: add one, or name it in NOT_OPTIONS")


def _shown_default(field: FieldInfo) -> str:
    value = field.get_default(call_default_factory=True)
    if value in ("", None):
        return ""  # the description says what an unset value means
    if isinstance(value, bool):
        value = "on" if value else "off"
    elif isinstance(value, list):
        value = ", ".join(map(str, value))  # also a value the option takes
    elif isinstance(value, enum.Enum):
        value = value.value
    return f" [default: {value}]"


class SettingsCommand(click.Command):
    """A command whose options are made from Settings when first needed (help, parsing): importing
    Settings (pydantic-settings) would otherwise slow every other `fleet` command."""

    _made = False
    selected: Callable[[str], bool] = staticmethod(serve_setting)

    def get_params(self, ctx: click.Context) -> list[click.Parameter]:
        if not self._made:
            self.params[:0] = settings_options(self.selected)
            self._made = True
        return super().get_params(ctx)

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        from services.settings import Settings

        prefix = str(Settings.model_config.get("env_prefix", ""))
        fields = Settings.model_fields
        with formatter.section("Settings without an option"):
            formatter.write_dl(
                [
                    (f"{prefix}{name.upper()}", f"{fields[name].description} ({why})")
                    for name, why in NOT_OPTIONS.items()
                    if self.selected(name)
                ]
            )
        super().format_epilog(ctx, formatter)


@click.command(cls=SettingsCommand)
def serve(**flags: object) -> None:
    """Run the service. Every flag can also be set as the FLEET_* variable named in its help,
    or in a TOML file named by FLEET_CONFIG."""
    from services.auth.bootstrap import check_auth_bind
    from services.rrd import limits
    from services.server import claim_ports
    from services.settings import load_settings
    from services.startup import split_addr
    from services.workers import worker_count

    settings = load_settings(**flags)
    limits.configure(settings.max_chunk_bytes, settings.decompress_budget_bytes)  # process-wide, like the memory
    hosts = []
    for addr in (settings.http_addr, settings.grpc_addr):
        try:
            hosts.append(split_addr(addr)[0])
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from exc
    auth_off = check_auth_bind(settings, hosts)  # auth off on a public address: refused, one line
    workers = worker_count(settings)  # more than one needs a Postgres catalog: refused, one line
    # Both ports, then the data dir, before anything is printed or made: a refused start is one line
    # and leaves no data dir, catalog or start-up lines behind.
    ports = claim_ports(settings)
    try:
        _serve(settings, ports, auth_off, workers)
    finally:
        for sock in ports:
            sock.close()


def _serve(settings: Settings, ports: tuple[socket.socket, socket.socket], auth_off: str | None, workers: int) -> None:
    """`fleet serve` once its ports are bound: the data dir held, the catalog ready, the node run."""
    import asyncio
    import logging

    from catalog.db import create_engine, is_embedded, prepare_for_service
    from services.server import release_reserve_if_full
    from services.server import serve as run_server
    from services.startup import hold_data_dir
    from services.workers import run_workers

    with hold_data_dir(settings.data_dir):  # one `fleet serve` per data dir, for the process's life
        release_reserve_if_full(settings)  # a full disk must not keep the catalog from opening
        # This engine (and its pooled connection) lives as long as the service: an embedded catalog's
        # file lock is then held from the start, not from the first write an idle service may not make
        # for a while, so `fleet db upgrade` or another `fleet serve` on that file is refused at once.
        engine = create_engine(settings.catalog_url, settings.catalog_timeout_s)
        try:
            done = prepare_for_service(engine)  # a catalog that is behind: one line naming `fleet db upgrade`
            if not is_embedded(engine):
                engine.dispose()  # a shared server catalog needs no such hold
            if done:
                click.echo(f"fleet: {done}")
            logging.basicConfig(level=logging.INFO, format="%(levelname)s:     %(name)s: %(message)s")
            logging.getLogger("apscheduler").setLevel(logging.ERROR)  # not a line per job run or skipped turn
            click.echo(
                f"fleet: data in {settings.data_dir.resolve()}, REST on http://{settings.http_addr}, "
                f"Rerun gRPC on rerun+http://{settings.grpc_addr}/proxy, durability {settings.durability}"
            )
            click.echo(f"fleet: {auth_off}" if auth_off else "fleet: auth on: every request needs a token")
            login = "" if auth_off else " (log in with a token: the admin token is in DATA_DIR/admin.token)"
            click.echo(f"fleet: web console on {console_address(settings)}{login}")
            if workers > 1:
                click.echo(f"fleet: {workers} worker processes share both ports (--workers)")
                run_workers(settings, workers, ports)
            else:
                asyncio.run(run_server(settings, ports=ports))
        finally:
            engine.dispose()


def console_address(settings: Settings) -> str:
    """Where a browser on this machine (or, with `public_url`, anywhere) opens the web console."""
    from services.startup import split_addr

    if settings.public_url:
        return settings.public_url.rstrip("/") + "/console/"
    host, port = split_addr(settings.http_addr)
    if host in ("0.0.0.0", "::", ""):
        host = "localhost"
    elif ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}/console/"
