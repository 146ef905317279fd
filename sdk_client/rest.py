"""REST client of the fleet service (what `fleet upload`, `fleet runs ...` use)."""

from __future__ import annotations

import datetime as dt
import getpass
import json
import re
import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx

from core.errors import ErrorCode, FleetError, InvalidArgumentError, UnavailableError

if TYPE_CHECKING:
    import pyarrow as pa

UPLOAD_PIECE = 1024 * 1024
# What a bearer token may hold (RFC 6750's b64token): a JWT of the depot always fits.
_TOKEN_CHARACTERS = re.compile(r"[A-Za-z0-9._~+/-]+=*")


class ServiceError(FleetError):
    """The service answered with an error; `status` is the HTTP status, `body` its JSON."""

    def __init__(self, message: str, status: int, body: dict[str, Any]) -> None:
        super().__init__(message)
        self.status = status
        self.body = body
        try:
            self.code = ErrorCode(body.get("code", "INTERNAL"))
        except ValueError:
            self.code = ErrorCode.INTERNAL


MCAP_MAGIC = b"\x89MCAP0\r\n"


class FleetClient:
    """The service's REST API. With a `token`, every request carries `Authorization: Bearer TOKEN`;
    the token is kept in that header only, never logged or shown."""

    def __init__(
        self, api_url: str, *, timeout: float = 300.0, user: str | None = None, token: str | None = None
    ) -> None:
        self.api_url = api_url.rstrip("/")
        # Who asks: with auth off, the service records this name with pins, restores and deletes
        # (with auth on, the token's subject).
        headers = {"X-Fleet-User": user or _default_user()}
        if token:
            headers["Authorization"] = f"Bearer {_checked_token(token)}"
        self._http = httpx.Client(base_url=self.api_url, timeout=timeout, headers=headers)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> FleetClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def upload(
        self,
        path: Path,
        on_progress: Callable[[int], None] | None = None,
        *,
        run_id: str | None = None,
        application: str | None = None,
        robot: str | None = None,
    ) -> dict[str, Any]:
        """Stream an .rrd or MCAP file to `POST /v1/uploads` (constant memory); returns the
        service's report, with the import it made. An MCAP file is converted by the depot before it
        answers, so its answer may take a while: no read timeout. `run_id`, `application` and
        `robot` apply to MCAP files."""
        with open(path, "rb") as fh:
            mcap = fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC

        def pieces() -> Iterator[bytes]:
            with open(path, "rb") as fh:
                while piece := fh.read(UPLOAD_PIECE):
                    yield piece
                    if on_progress is not None:
                        on_progress(len(piece))

        asked = {"run_id": run_id, "application": application, "robot": robot}
        params = {"name": path.name, **{k: v for k, v in asked.items() if v is not None}}
        return self._request(
            "POST",
            "/v1/uploads",
            content=pieces(),
            params=params,
            headers={"Content-Type": "application/octet-stream" if mcap else "application/vnd.rerun.rrd"},
            timeout=httpx.Timeout(60.0, read=None) if mcap else httpx.USE_CLIENT_DEFAULT,
        )

    def imports(self, **params: Any) -> dict[str, Any]:
        """Uploads newest first (`GET /v1/imports`: state, kind, robot, limit, before)."""
        return self._request("GET", "/v1/imports", params={k: v for k, v in params.items() if v is not None})

    def import_(self, import_id: str) -> dict[str, Any]:
        return self._request("GET", f"/v1/imports/{import_id}")

    def retry_import(self, import_id: str) -> dict[str, Any]:
        """Convert a failed MCAP import again from its quarantined original (`POST .../retry`)."""
        return self._request("POST", f"/v1/imports/{import_id}/retry", timeout=httpx.Timeout(60.0, read=None))

    def import_original(self, import_id: str, out: Path) -> int:
        """A failed import's quarantined original, written to `out` (admin); bytes written."""
        return self._save(f"/v1/imports/{import_id}/original", out)

    def _save(self, url: str, out: Path) -> int:
        """The body of a GET of `url`, streamed into the file `out`; bytes written."""
        written = 0
        try:
            with self._http.stream("GET", url) as response:
                _check(response)
                with open(out, "wb") as fh:
                    for piece in response.iter_bytes():
                        fh.write(piece)
                        written += len(piece)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from exc
        return written

    def runs(self, **params: Any) -> dict[str, Any]:
        """`GET /v1/runs` with its filters (robot, application, since, until, status, tier, entity,
        property, metric, tag, event, sort, limit, cursor); repeatable ones as lists, e.g.
        `runs(metric=["distance_m>100"], tag=["night-shift"], sort="-metric.distance_m")`."""
        return self._request("GET", "/v1/runs", params={k: v for k, v in params.items() if v not in (None, [], ())})

    def run(self, run_id: str) -> dict[str, Any]:
        return self._request("GET", f"/v1/runs/{run_id}")

    def recording_url(self, run_id: str, **params: Any) -> str:
        query = httpx.QueryParams({k: v for k, v in params.items() if v not in (None, [], ())})
        return f"{self.api_url}/v1/runs/{run_id}/recording.rrd" + (f"?{query}" if query else "")

    def recording_link(self, run_id: str, expires_in: float | None = None, **params: Any) -> dict[str, Any]:
        """A signed, expiring link to `recording_url(run_id, **params)` that opens without a header
        (`POST /v1/runs/RUN/links`): `{url, expires_at}`; with auth off, `expires_at` is None and
        the plain URL opens it. `expires_in` in seconds (default: the service's FLEET_LINK_TTL_S)."""
        query = {k: v for k, v in params.items() if v not in (None, [], ())}
        if expires_in is not None:
            query["expires_in"] = expires_in
        return self._request("POST", f"/v1/runs/{run_id}/links", params=query)

    def check_recording(self, run_id: str, **params: Any) -> list[str]:
        """Ask the service whether `recording_url(run_id, **params)` would answer, without taking the
        data: it checks every parameter before the first byte, so its error (a 404, or a 422 naming a
        bad time or timeline) comes with the response headers, and the body is left unread. Returns
        its warnings (filters that match no entity of the run)."""
        try:
            with self._http.stream("GET", self.recording_url(run_id, **params)) as response:
                _check(response)
                return recording_warnings(response)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from exc

    def download(
        self,
        run_id: str,
        out: Path,
        on_progress: Callable[[int], None] | None = None,
        on_warning: Callable[[str], None] | None = None,
        **params: Any,
    ) -> int:
        """Stream a run's recording to `out`; returns the bytes written. `on_warning` is told of
        each filter that matches no entity of the run, before the data."""
        url = self.recording_url(run_id, **params)
        written = 0
        try:
            with self._http.stream("GET", url) as response:
                _check(response)
                for warning in recording_warnings(response):
                    if on_warning is not None:
                        on_warning(warning)
                with open(out, "wb") as fh:
                    for piece in response.iter_bytes():
                        fh.write(piece)
                        written += len(piece)
                        if on_progress is not None:
                            on_progress(len(piece))
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from exc
        return written

    def sql(self, query: str) -> pa.Table:
        """Run a read-only SQL query (`POST /v1/sql`); the answer as a pyarrow Table."""
        import pyarrow as pa

        content = self.sql_bytes(query, "arrow")
        with pa.ipc.open_stream(content) as reader:
            return reader.read_all()

    def sql_bytes(self, query: str, fmt: str = "json") -> bytes:
        """The answer to a SQL query encoded as `fmt`: json, csv, arrow (IPC stream) or parquet."""
        try:
            response = self._http.post("/v1/sql", json={"query": query}, params={"format": fmt}, timeout=None)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from exc
        _check(response)
        return response.content

    def retention(self) -> dict[str, Any]:
        """Policies, settings and recent job runs (`GET /v1/retention`)."""
        return self._request("GET", "/v1/retention")

    def retention_plan(self, actions: list[str] | None = None) -> dict[str, Any]:
        return self._request("GET", "/v1/retention/plan", params={"action": actions or []})

    def retention_run(self, actions: list[str] | None = None) -> Iterator[dict[str, Any]]:
        """Do what is due now; yields the service's progress events as they come."""
        return self._events("POST", "/v1/retention/run", params={"action": actions or []})

    def rebuild_catalog(self) -> Iterator[dict[str, Any]]:
        """Add to the catalog every sealed run the stores hold that it lacks; yields progress events."""
        return self._events("POST", "/v1/catalog/rebuild")

    def scrub_secrets(self, dry_run: bool = False) -> Iterator[dict[str, Any]]:
        """Seal again without them the warm runs whose properties hold secret-like fields (filed
        before ingest stripped them everywhere); yields progress events."""
        return self._events("POST", "/v1/catalog/scrub-secrets" + ("?dry_run=true" if dry_run else ""))

    def pin(self, run_id: str, pinned: bool = True) -> dict[str, Any]:
        return self._request("POST" if pinned else "DELETE", f"/v1/runs/{run_id}/pin")

    def promote(self, run_id: str) -> dict[str, Any]:
        """Seal a closed hot run into the warm tier now (`POST /v1/runs/RUN/promote`)."""
        return self._request("POST", f"/v1/runs/{run_id}/promote", timeout=None)

    def restore(self, run_id: str) -> dict[str, Any]:
        return self._request("POST", f"/v1/runs/{run_id}/restore")

    def delete_run(self, run_id: str, force: bool = False) -> dict[str, Any]:
        """Delete a sealed run now (admin). A run a dataset snapshot uses is refused (409 naming the
        snapshots) unless `force`: its episodes then answer `missing`."""
        return self._request("DELETE", f"/v1/runs/{run_id}", params={"force": "true"} if force else None)

    def whoami(self) -> dict[str, Any]:
        """Who the token stands for and what it may do (`GET /v1/whoami`)."""
        return self._request("GET", "/v1/whoami")

    def create_token(
        self,
        scopes: list[str],
        *,
        robot: str | None = None,
        name: str | None = None,
        expires_in_s: float | None = None,
        hosts: list[str] | None = None,
    ) -> dict[str, Any]:
        """A new token (`POST /v1/tokens`, admin): its record, `allowed_hosts` and, this once, `token`."""
        body = {"scopes": scopes, "robot": robot, "name": name, "expires_in_s": expires_in_s, "hosts": hosts or None}
        return self._request("POST", "/v1/tokens", json=body)

    def tokens(self, include_revoked: bool = False) -> dict[str, Any]:
        """`{"tokens": [...]}`: what each token grants, never the token (`GET /v1/tokens`, admin)."""
        return self._request("GET", "/v1/tokens", params={"revoked": "true"} if include_revoked else {})

    def revoke_token(self, token_id: str) -> dict[str, Any]:
        """Revoke a token (`DELETE /v1/tokens/ID`, admin); answers its record."""
        return self._request("DELETE", f"/v1/tokens/{token_id}")

    # --- webhooks (admin) ------------------------------------------------------------------------

    def add_webhook(self, url: str, on: list[str], body_format: str = "json") -> dict[str, Any]:
        """A new webhook (`POST /v1/webhooks`): its record and, this once, its signing `secret`."""
        return self._request("POST", "/v1/webhooks", json={"url": url, "on": on, "format": body_format})

    def webhooks(self) -> dict[str, Any]:
        """`{"webhooks": [...]}`: where each goes and what it is told of, never its secret."""
        return self._request("GET", "/v1/webhooks")

    def remove_webhook(self, webhook_id: str) -> dict[str, Any]:
        return self._request("DELETE", f"/v1/webhooks/{webhook_id}")

    def webhook_deliveries(self, webhook_id: str, limit: int = 50, cursor: str | None = None) -> dict[str, Any]:
        """A page of a webhook's deliveries, newest first, and `next_cursor`."""
        params: dict[str, Any] = {"limit": limit, **({"cursor": cursor} if cursor else {})}
        return self._request("GET", f"/v1/webhooks/{webhook_id}/deliveries", params=params)

    # --- robots' own tiers: what a robot's agent asks, and pulls from robots ----------------------

    def held(self, run_id: str, chunk_ids: list[str]) -> dict[str, Any]:
        """Which of a run's chunks the depot holds (`POST /v1/runs/RUN/held`; 1 to 100000 ids of 32
        lowercase hex digits): `{run, robot, tier, status, accepts_data, missing, unsealed, sealed}`."""
        return self._request("POST", f"/v1/runs/{run_id}/held", json={"chunk_ids": chunk_ids})

    def request_pull(
        self,
        run_id: str,
        *,
        include: list[str] | None = None,
        exclude: list[str] | None = None,
        timeline: str | None = None,
        start: str | None = None,
        end: str | None = None,
    ) -> dict[str, Any]:
        """Ask the run's robot to send (part of) it (`POST /v1/runs/RUN/pull`, write); the pull
        queued, or the pending or sending one that asks the same."""
        body = {"include": include or [], "exclude": exclude or [], "timeline": timeline, "start": start, "end": end}
        pull: dict[str, Any] = self._request("POST", f"/v1/runs/{run_id}/pull", json=body)["pull"]
        return pull

    def pulls(self, state: str | None = None, robot: str | None = None, limit: int = 100) -> list[dict[str, Any]]:
        """Pulls by state and robot, oldest first (`GET /v1/pulls`; a robot's token: its own robot's)."""
        params = {k: v for k, v in {"state": state, "robot": robot, "limit": limit}.items() if v is not None}
        found: list[dict[str, Any]] = self._request("GET", "/v1/pulls", params=params)["pulls"]
        return found

    def run_pulls(self, run_id: str) -> list[dict[str, Any]]:
        """A run's pulls, newest first (`GET /v1/runs/RUN/pulls`)."""
        found: list[dict[str, Any]] = self._request("GET", f"/v1/runs/{run_id}/pulls")["pulls"]
        return found

    def pull_progress(
        self, pull_id: str, *, state: str, chunks_sent: int, bytes_sent: int, error: str | None = None
    ) -> dict[str, Any]:
        """Report how far the agent got (`POST /v1/pulls/PULL/progress`; state sending, done or
        failed); the pull as it is now. A done, failed or cancelled pull raises ServiceError (409)."""
        body = {"state": state, "chunks_sent": chunks_sent, "bytes_sent": bytes_sent, "error": error}
        pull: dict[str, Any] = self._request("POST", f"/v1/pulls/{pull_id}/progress", json=body)["pull"]
        return pull

    def cancel_pull(self, pull_id: str) -> dict[str, Any]:
        """Cancel a pending or sending pull (`POST /v1/pulls/PULL/cancel`, write); the pull."""
        pull: dict[str, Any] = self._request("POST", f"/v1/pulls/{pull_id}/cancel")["pull"]
        return pull

    def report_robot_copy(self, run_id: str, **fields: Any) -> dict[str, Any]:
        """What the robot holds of a run (`PUT /v1/runs/RUN/robot-copy`): chunks, bytes,
        local_only_chunks, local_only_bytes, local_only_entities, keeps_until (a datetime or
        ISO-8601); the copy as stored. 404 (retry later) while the catalog lacks the run."""
        body = {k: v.isoformat() if isinstance(v, dt.datetime) else v for k, v in fields.items()}
        copy: dict[str, Any] = self._request("PUT", f"/v1/runs/{run_id}/robot-copy", json=body)["robot_copy"]
        return copy

    def forget_robot_copy(self, run_id: str) -> dict[str, Any]:
        """The robot deleted its copy of a run (`DELETE /v1/runs/RUN/robot-copy`): `{run, removed,
        robot_copy: None}`."""
        return self._request("DELETE", f"/v1/runs/{run_id}/robot-copy")

    # --- the corpus: rules, events, tags ------------------------------------------------------------

    def apply_rules(self, text: str) -> dict[str, Any]:
        """Apply a rules file (`PUT /v1/rules`, the TOML as the body): the version it made (or the
        running one, `changed` false, for the same text). A bad file: a 422 whose body's `problems`
        name every one by line and field."""
        return self._request("PUT", "/v1/rules", content=text.encode(), headers={"Content-Type": "application/toml"})

    def rules(self, version: int | None = None) -> dict[str, Any]:
        """The running rules (`GET /v1/rules`), or an older version."""
        return self._request("GET", "/v1/rules", params={"version": version} if version is not None else None)

    def rules_backfill(self) -> Iterator[dict[str, Any]]:
        """Evaluate now every stored run the running rules have not (`POST /v1/rules/backfill`);
        yields progress events, the last one the summary."""
        return self._events("POST", "/v1/rules/backfill")

    def rules_history(self) -> list[dict[str, Any]]:
        """Every version of the rules, newest first, with who applied it and when."""
        versions: list[dict[str, Any]] = self._request("GET", "/v1/rules/history")["versions"]
        return versions

    def events(self, **params: Any) -> dict[str, Any]:
        """`GET /v1/events` with its filters (kind, robot, run, severity, origin, source, since, until,
        pending, limit, cursor): `{events, next_cursor}`. `pending=True`: only events whose window is
        asked of the robot and not at the depot yet."""
        return self._request("GET", "/v1/events", params={k: v for k, v in params.items() if v not in (None, [], ())})

    def event(self, event_id: str) -> dict[str, Any]:
        return self._request("GET", f"/v1/events/{event_id}")

    def pull_event(self, event_id: str) -> dict[str, Any]:
        """Ask the robot for the window of an event a trigger pulled (`POST /v1/events/EVENT/pull`,
        write): the pull queued, or the pending or sending one of the event."""
        pull: dict[str, Any] = self._request("POST", f"/v1/events/{event_id}/pull")["pull"]
        return pull

    def report_triggered(self, run_id: str, body: dict[str, Any]) -> dict[str, Any]:
        """A robot's agent reports a trigger it fired (`POST /v1/runs/RUN/triggered`; body: pull_id,
        rules_version, event, window, priority, state, chunks_sent, bytes_sent, error): `{event, pull}`,
        the pull it reports progress on."""
        return self._request("POST", f"/v1/runs/{run_id}/triggered", json=body)

    def run_events(self, run_id: str) -> list[dict[str, Any]]:
        events: list[dict[str, Any]] = self._request("GET", f"/v1/runs/{run_id}/events")["events"]
        return events

    def annotate(self, run_id: str, timeline: str, start: str | int, **fields: Any) -> dict[str, Any]:
        """A person's event on a run (`POST /v1/runs/RUN/events`): fields end, label, note, severity,
        kind."""
        body = {"timeline": timeline, "start": start, **{k: v for k, v in fields.items() if v is not None}}
        return self._request("POST", f"/v1/runs/{run_id}/events", json=body)

    def tag(self, run_id: str, tags: list[str]) -> dict[str, Any]:
        """`POST /v1/runs/RUN/tags`: the run's tags after, each with who added it, and those `added`."""
        return self._request("POST", f"/v1/runs/{run_id}/tags", json={"tags": tags})

    def untag(self, run_id: str, tags: list[str]) -> dict[str, Any]:
        """`DELETE /v1/runs/RUN/tags`: the run's tags after, and those `removed`."""
        return self._request("DELETE", f"/v1/runs/{run_id}/tags", params={"tag": tags})

    # --- dataset snapshots ----------------------------------------------------------------------------

    def create_dataset(self, name: str, **selection: Any) -> dict[str, Any]:
        """Resolve a selection into the next version of dataset `name` (`POST /v1/datasets`; fields as
        `GET /v1/runs` filters plus event_window, include, exclude, timeline, fps, split, seed): the
        version's summary (`ref` NAME@N, episodes, runs, chunks, bytes, splits, skipped)."""
        body = {"name": name, **{k: v for k, v in selection.items() if v not in (None, [], (), {})}}
        return self._request("POST", "/v1/datasets", json=body, timeout=None)

    def datasets(self) -> list[dict[str, Any]]:
        """Every dataset snapshot with its latest version."""
        found: list[dict[str, Any]] = self._request("GET", "/v1/datasets")["datasets"]
        return found

    def dataset(self, name: str) -> dict[str, Any]:
        """A snapshot with its versions, newest first."""
        return self._request("GET", f"/v1/datasets/{name}")

    def dataset_version(
        self, name: str, version: int, limit: int = 100, cursor: str | None = None, chunk_ids: bool = False
    ) -> dict[str, Any]:
        """One version: its selection and a page of episodes (`episodes_page`, `next_cursor`)."""
        params: dict[str, Any] = {"limit": limit}
        if cursor is not None:
            params["cursor"] = cursor
        if chunk_ids:
            params["chunk_ids"] = "true"
        return self._request("GET", f"/v1/datasets/{name}/{version}", params=params)

    def download_episode(self, name: str, version: int, episode: int, out: Path) -> int:
        """The chunks one episode of NAME@VERSION reads, as an RRD file at `out`; bytes written."""
        return self._save(f"/v1/datasets/{name}/{version}/episodes/{episode}/recording.rrd", out)

    def export_dataset(self, dataset: str, to: str, **options: Any) -> dict[str, Any]:
        """Queue NAME@N's export by the depot into `to` (`POST /v1/exports`): the job."""
        body = {"dataset": dataset, "to": to, **{k: v for k, v in options.items() if v is not None}}
        return self._request("POST", "/v1/exports", json=body)

    def exports(self, dataset: str | None = None, limit: int = 50) -> list[dict[str, Any]]:
        """Export jobs, newest first (of NAME or NAME@N if given)."""
        params: dict[str, Any] = {"limit": limit, **({"dataset": dataset} if dataset else {})}
        found: list[dict[str, Any]] = self._request("GET", "/v1/exports", params=params)["exports"]
        return found

    def export(self, job_id: str) -> dict[str, Any]:
        """One export job: state, progress, quality report."""
        return self._request("GET", f"/v1/exports/{job_id}")

    def cancel_export(self, job_id: str) -> dict[str, Any]:
        return self._request("DELETE", f"/v1/exports/{job_id}")

    def _events(self, method: str, url: str, **kwargs: Any) -> Iterator[dict[str, Any]]:
        try:
            with self._http.stream(method, url, timeout=None, **kwargs) as response:
                _check(response)
                for line in response.iter_lines():
                    if line.strip():
                        yield json.loads(line)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from exc

    def _request(self, method: str, url: str, **kwargs: Any) -> dict[str, Any]:
        try:
            response = self._http.request(method, url, **kwargs)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from exc
        _check(response)
        try:
            body: dict[str, Any] = response.json()
        except ValueError:
            body = {"message": response.text[:500]}
        return body

    def _unreachable(self, exc: Exception) -> UnavailableError:
        return UnavailableError(
            f"cannot reach the fleet service at {self.api_url} ({exc}); is it running? set FLEET_API_URL"
        )


def _check(response: httpx.Response) -> None:
    """Raise the service's error (its code and message) for a 4xx/5xx answer."""
    if response.status_code < 400:
        return
    response.read()
    try:
        body = response.json()
    except ValueError:
        body = {"message": response.text[:500]}
    raise ServiceError(str(body.get("message", response.reason_phrase)), response.status_code, body)


def recording_warnings(response: httpx.Response) -> list[str]:
    """What a recording's answer warns of (`Fleet-Warnings`, a JSON list): filters that match no
    entity of the run, so the file holds more (or less) than the caller meant."""
    raw = response.headers.get("fleet-warnings")
    if not raw:
        return []
    try:
        warnings = json.loads(raw)
    except ValueError:
        return [raw]
    return [str(w) for w in warnings] if isinstance(warnings, list) else [str(warnings)]


def _checked_token(token: str) -> str:
    """A token fit for a header. A wrong one is refused here naming where tokens come from, not by
    the HTTP library, whose error would quote the header, token and all."""
    token = token.strip()
    if not _TOKEN_CHARACTERS.fullmatch(token):
        raise InvalidArgumentError(
            "the token holds characters no token has (spaces, quotes, line breaks?): copy it whole, "
            "as `fleet tokens create` printed it"
        )
    return token


def _default_user() -> str:
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "unknown"
    return f"{user}@{socket.gethostname()}"
