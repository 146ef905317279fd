"""How CLI commands reach the service: its address (`--api-url`, FLEET_API_URL) and the token they
send, found in one place, in this order:

1. FLEET_TOKEN;
2. else `$FLEET_DATA_DIR/admin.token` (FLEET_DATA_DIR defaults to ./fleet-data, as for `fleet
   serve`), the admin token the service wrote at its first start, when it exists and can be read,
   and only when the service is reached on this machine (a loopback address) or on a host the
   token names in its `allowed_hosts`: a command run beside the service finds it, and it is never
   sent to another host by mistake;
3. else none (fine for a service with auth off).

A 401 becomes one line saying which token was sent (never the token) and how to get one."""

from __future__ import annotations

import contextlib
import datetime as dt
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

import click

from core.errors import InvalidArgumentError, UnauthenticatedError
from services.auth import ADMIN_TOKEN_FILE
from services.startup import is_loopback

if TYPE_CHECKING:
    from sdk_client.rest import FleetClient

TOKEN_ENV = "FLEET_TOKEN"
DATA_DIR_ENV = "FLEET_DATA_DIR"
DEFAULT_DATA_DIR = "./fleet-data"
HOW_TO_GET_ONE = "an admin makes one with `fleet tokens create`"

api_option = click.option(
    "--api-url",
    envvar="FLEET_API_URL",
    default="http://127.0.0.1:8080",
    show_default=True,
    help="Where the service answers (FLEET_API_URL). Its token: FLEET_TOKEN, else "
    "$FLEET_DATA_DIR/admin.token on the service's machine.",
)


@dataclass(frozen=True)
class TokenSource:
    """The token a command sends, and where it came from (said when the service refuses it)."""

    token: str | None
    origin: str  # "FLEET_TOKEN", the admin token file's path, or "" for none
    note: str = ""  # why a token file that exists was not used


def resolve_token(api_url: str, env: Mapping[str, str]) -> TokenSource:
    """The token to send to `api_url`: FLEET_TOKEN, else the data dir's admin token, else none."""
    given = env.get(TOKEN_ENV, "").strip()
    if given:
        return TokenSource(given, TOKEN_ENV)
    path = Path(env.get(DATA_DIR_ENV) or DEFAULT_DATA_DIR) / ADMIN_TOKEN_FILE
    try:
        token = path.read_text().strip()
    except FileNotFoundError:
        return TokenSource(None, "")
    except (OSError, UnicodeDecodeError) as exc:
        return TokenSource(None, "", f"{path} could not be read ({type(exc).__name__})")
    if not token:
        return TokenSource(None, "", f"{path} is empty")
    host = urlsplit(api_url).hostname or ""
    if not (is_loopback(host) or host in _allowed_hosts(token)):
        return TokenSource(
            None, "", f"{path} was not sent to {host}: neither a loopback address nor in the token's allowed_hosts"
        )
    return TokenSource(token, str(path))


def _allowed_hosts(token: str) -> list[str]:
    """The hosts a depot token names for itself (its claims, read without checking the signature:
    only the service can check it, and this decides nothing but where to send it)."""
    import jwt

    try:
        hosts = jwt.decode(token, options={"verify_signature": False}).get("allowed_hosts")
    except jwt.InvalidTokenError:
        return []
    return [h for h in hosts if isinstance(h, str)] if isinstance(hosts, list) else []


@contextlib.contextmanager
def client(api_url: str) -> Iterator[FleetClient]:
    """A REST client of the service at `api_url` with the resolved token; a 401 from the service
    inside the block leaves it as one line naming FLEET_TOKEN and `fleet tokens create`."""
    from sdk_client.rest import FleetClient, ServiceError

    source = resolve_token(api_url, os.environ)
    try:
        fleet = FleetClient(api_url, token=source.token)
    except InvalidArgumentError as exc:
        raise InvalidArgumentError(f"{source.origin}: {exc.message}") from None
    with fleet:
        try:
            yield fleet
        except ServiceError as exc:
            if exc.status == 401:
                raise UnauthenticatedError(unauthenticated_message(exc.message, source), "refused") from None
            raise


def unauthenticated_message(refusal: str, source: TokenSource) -> str:
    """The service's refusal, with which token was sent and how to send a good one, on one line."""
    if source.origin:
        sent = f"the token in {TOKEN_ENV}" if source.origin == TOKEN_ENV else f"the admin token in {source.origin}"
        return f"the service refused {sent}: {refusal} (set {TOKEN_ENV} to a valid token; {HOW_TO_GET_ONE})"
    why = f" ({source.note})" if source.note else ""
    return (
        f"the service needs a token and none was sent{why}: set {TOKEN_ENV} ({HOW_TO_GET_ONE}), or, on the "
        f"service's machine, {DATA_DIR_ENV} to its data dir (its {ADMIN_TOKEN_FILE} is read)"
    )


class Duration(click.ParamType[dt.timedelta]):
    """A click parameter read as a duration (90d, 12h, 30m, 45s, 2w): a timedelta."""

    name = "DURATION"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> dt.timedelta:
        if isinstance(value, dt.timedelta):
            return value
        from core.clock import parse_duration

        try:
            return parse_duration(str(value))
        except InvalidArgumentError as exc:
            self.fail(exc.message, param, ctx)
