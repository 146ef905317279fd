"""Signed links to runs' recordings, as the run API and `fleet view` hand them out."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog.db import session_scope
from catalog.queries import require_run
from core.clock import iso_utc
from core.errors import BadParameterError
from services.auth.scopes import Principal
from services.auth.tokens import Auth
from services.hot.read import HotRuns

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
