"""Signed links to runs' recordings, as the run API and `fleet view` hand them out, and the base
URL written into them."""

from __future__ import annotations

import datetime as dt
import socket
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from sqlalchemy.orm import Session, sessionmaker
from starlette.requests import Request

from catalog.db import session_scope
from catalog.queries import require_run
from core.clock import iso_utc
from core.errors import BadParameterError
from services.auth.scopes import Principal
from services.auth.tokens import Auth
from services.hot.read import HotRuns
from services.settings import Settings
from services.startup import split_addr

# The recording's parameters a link may carry (GET /v1/runs/RUN/recording.rrd).
RECORDING_PARAMETERS = frozenset(
    {"include", "exclude", "blueprint", "timeline", "start", "end", "latest_at", "follow", "exact"}
)
MAX_LIFETIME_S = 7 * 24 * 3600.0


@dataclass
class RunLookup:
    hot_runs: HotRuns | None
    catalog: sessionmaker[Session]

    def require(self, run_id: str) -> None:
        """404 unless the run is hot here or in the catalog."""
        if self.hot_runs is not None and self.hot_runs.hot_recording(run_id) is not None:
            return
        with session_scope(self.catalog) as session:
            require_run(session, run_id)


def lifetime(expires_in: float | None, default_s: float) -> dt.timedelta:
    seconds = default_s if expires_in is None else expires_in
    if not 0 < seconds <= MAX_LIFETIME_S:
        raise BadParameterError("expires_in", f"a link lasts from 1 second to 7 days ({MAX_LIFETIME_S:g} s)")
    return dt.timedelta(seconds=seconds)


def recording_link(
    auth: Auth,
    principal: Principal,
    runs: RunLookup,
    run_id: str,
    params: list[tuple[str, str]],
    ttl: dt.timedelta,
    base_url: str,
) -> dict[str, Any]:
    unknown = sorted({k for k, _ in params} - RECORDING_PARAMETERS)
    if unknown:
        raise BadParameterError(unknown[0], f"not a recording parameter: use {', '.join(sorted(RECORDING_PARAMETERS))}")
    runs.require(run_id)
    expires_at = auth.clock().replace(microsecond=0) + ttl
    path = auth.sign_link(principal, run_id, params, expires_at)
    return {
        "run": run_id,
        "url": base_url.rstrip("/") + path,
        "expires_at": iso_utc(expires_at) if auth.enabled else None,
    }


WILDCARDS = ("0.0.0.0", "::", "")


def public_base(settings: Settings, known_hosts: Iterable[str], host_header: str | None, scheme: str) -> str:
    """The base URL of the links the depot hands out: FLEET_PUBLIC_URL when set. Else the address
    the request came to, but only when its host is one the depot is known by (`known_hosts`:
    FLEET_PUBLIC_HOSTS, by default localhost, 127.0.0.1 and this machine's names; or the address
    the REST port binds) on that port or none: a `Host` header is the client's to write, and a link
    made from a forged one would send its reader, with the link's signature, elsewhere. Else the
    address the REST port binds (this machine's name for a wildcard bind)."""
    if settings.public_url:
        return settings.public_url.rstrip("/")
    bind_host, port = split_addr(settings.http_addr)
    named = _host_and_port(host_header)
    if named is not None:
        host, given_port = named
        known = {h.lower() for h in known_hosts} | ({bind_host.lower()} - set(WILDCARDS))
        if host in known and given_port in (None, port):
            return f"{scheme}://{_netloc(host, given_port)}"
    host = socket.gethostname() if bind_host in WILDCARDS else bind_host
    return f"http://{_netloc(host, port)}"


def request_base(request: Request) -> str:
    """`public_base` for a request of the REST app (its settings, the depot's known hosts)."""
    state = request.app.state
    return public_base(state.settings, state.auth.public_hosts, request.headers.get("host"), request.url.scheme)


def _host_and_port(header: str | None) -> tuple[str, int | None] | None:
    """A Host header's host (lower case, an IPv6 address without brackets) and port; None if it is
    not one."""
    if not header:
        return None
    try:
        parts = urlsplit(f"//{header.strip()}")
        host, port = parts.hostname, parts.port
    except ValueError:  # a port that is no number, a bracket left open
        return None
    if not host or parts.username is not None or parts.password is not None or parts.path:
        return None
    return host, port


def _netloc(host: str, port: int | None) -> str:
    shown = f"[{host}]" if ":" in host else host
    return shown if port is None else f"{shown}:{port}"
