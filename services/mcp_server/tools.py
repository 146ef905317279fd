"""The depot's MCP server: tools an assistant calls to find runs, read their events, logs and
signals, run SQL, open the viewer, and (with a `write` token) tag, annotate and ask robots for data.

Every tool is one REST call with the caller's token (`depot.DepotApi`): what a token may not do
over REST it may not do here. Descriptions are written for a model: what the tool answers, how to
narrow it, and which tool to call next.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from typing import Annotated, Any

from mcp.server.fastmcp import Context, FastMCP
from mcp.server.fastmcp.exceptions import ToolError
from mcp.server.transport_security import TransportSecuritySettings
from mcp.types import ToolAnnotations
from pydantic import Field

from core.ids import is_id
from services import __version__
from services.mcp_server.depot import DepotApi, bounded

Connect = Callable[[Context[Any, Any, Any]], AbstractAsyncContextManager[DepotApi]]

INSTRUCTIONS = """\
A fleet telemetry depot: robots' recordings (Rerun runs), filed by robot and day, with events
(rule-made, robot-made, people's annotations), run metrics and tags, and SQL over the telemetry.
Start with find_runs or list_events; read a run with get_run, its logs around a moment with
run_logs, a signal with scalar_series; give people viewer_link's URL to look for themselves.
Times are ISO-8601 (UTC) unless a tool says otherwise. Answers are cut to a bounded size and say so
("truncated")."""

READ = ToolAnnotations(readOnlyHint=True, openWorldHint=False)
WRITE = ToolAnnotations(readOnlyHint=False, destructiveHint=False, idempotentHint=True, openWorldHint=False)
LEVELS = ("TRACE", "DEBUG", "INFO", "WARN", "ERROR", "CRITICAL")

RunId = Annotated[str, Field(description="a run id, as find_runs answers it", max_length=128)]
Limit = Annotated[int, Field(ge=1, le=100, description="most items to answer")]


def build_server(connect: Connect, **http: Any) -> FastMCP[Any]:
    """The MCP server whose tools reach the depot through `connect` (the caller's REST API); `http`:
    its streamable HTTP settings, when served over HTTP."""
    # Bearer tokens are not ambient credentials a rebinding page could use: no Host check, so the
    # depot answers under whatever name it is reached by.
    security = TransportSecuritySettings(enable_dns_rebinding_protection=False)
    server = FastMCP(f"fleet-depot {__version__}", instructions=INSTRUCTIONS, transport_security=security, **http)

    @server.tool(annotations=READ)
    async def find_runs(
        ctx: Context[Any, Any, Any],
        robot: Annotated[list[str] | None, Field(description="robot ids (any of them)")] = None,
        application: Annotated[list[str] | None, Field(description="application ids (any of them)")] = None,
        since: Annotated[str | None, Field(description="started at or after, ISO-8601")] = None,
        until: Annotated[str | None, Field(description="started before, ISO-8601")] = None,
        tier: Annotated[str | None, Field(description="hot | warm | cold | deleted")] = None,
        status: Annotated[str | None, Field(description="live | closed")] = None,
        entity: Annotated[list[str] | None, Field(description="has an entity: /world/** or an exact path")] = None,
        prop: Annotated[
            list[str] | None, Field(description="recording properties NAME.FIELD=VALUE, e.g. fleet.site=dock-2")
        ] = None,
        metric: Annotated[
            list[str] | None, Field(description="run metric conditions, all must hold: e.g. distance_m>100")
        ] = None,
        tag: Annotated[list[str] | None, Field(description="tags the run has (all of them)")] = None,
        event: Annotated[
            list[str] | None, Field(description="event kinds the run has at least one of each (e.g. intervention)")
        ] = None,
        sort: Annotated[str, Field(description="-started_at (newest first), started_at, or metric.NAME")] = (
            "-started_at"
        ),
        limit: Limit = 20,
        cursor: Annotated[str | None, Field(description="next_cursor of the previous answer: its next page")] = None,
    ) -> dict[str, Any]:
        """Find runs (recordings) by robot, application, time, tier, entities, properties, metrics,
        tags and event kinds. Answers each run's id, robot, times, size and tier, and next_cursor
        when there are more; get_run gives one run's details."""
        params = {
            "robot": robot,
            "application": application,
            "since": since,
            "until": until,
            "tier": tier,
            "status": status,
            "entity": entity,
            "property": prop,
            "cursor": cursor,
            "metric": metric,
            "tag": tag,
            "event": event,
            "sort": sort,
            "limit": limit,
        }
        async with connect(ctx) as api:
            return bounded(await api.call("GET", "/v1/runs", params=params))

    @server.tool(annotations=READ)
    async def get_run(ctx: Context[Any, Any, Any], run_id: RunId) -> dict[str, Any]:
        """One run's details: robot, application, times, tier, entities (what was logged), timelines,
        properties, metrics, tags and event counts."""
        async with connect(ctx) as api:
            return bounded(await api.call("GET", f"/v1/runs/{_run(run_id)}"))

    @server.tool(annotations=READ)
    async def list_events(
        ctx: Context[Any, Any, Any],
        kind: Annotated[list[str] | None, Field(description="event kinds (e.g. intervention)")] = None,
        robot: Annotated[list[str] | None, Field(description="robot ids")] = None,
        run: Annotated[list[str] | None, Field(description="run ids")] = None,
        severity: Annotated[list[str] | None, Field(description="info | warn | error")] = None,
        since: Annotated[str | None, Field(description="recorded at or after, ISO-8601")] = None,
        until: Annotated[str | None, Field(description="recorded before, ISO-8601")] = None,
        limit: Limit = 20,
    ) -> dict[str, Any]:
        """Events across the fleet, newest first: time ranges on runs that rules, robots or people
        marked (kind, severity, label), each with a viewer link to its window."""
        params = {
            "kind": kind,
            "robot": robot,
            "run": run,
            "severity": severity,
            "since": since,
            "until": until,
            "limit": limit,
        }
        async with connect(ctx) as api:
            return bounded(await api.call("GET", "/v1/events", params=params))

    @server.tool(annotations=READ)
    async def run_logs(
        ctx: Context[Any, Any, Any],
        run_id: RunId,
        around: Annotated[str, Field(description="the moment, ISO-8601 (an event's start, say)")],
        before_s: Annotated[float, Field(ge=0, le=3600, description="seconds before it")] = 30.0,
        after_s: Annotated[float, Field(ge=0, le=3600, description="seconds after it")] = 10.0,
        min_level: Annotated[str | None, Field(description="TRACE | DEBUG | INFO | WARN | ERROR")] = None,
        limit: Limit = 50,
    ) -> dict[str, Any]:
        """A run's text log lines (TextLog) around a moment, in time order: what the robot said
        just before and after something happened."""
        moment = _instant(around)
        start, end = moment - dt.timedelta(seconds=before_s), moment + dt.timedelta(seconds=after_s)
        levels = ""
        if min_level is not None:
            if min_level.upper() not in LEVELS:
                raise ToolError(f"min_level {min_level!r} is not one of {', '.join(LEVELS)}")
            wanted = ", ".join(f"'{lv}'" for lv in LEVELS[LEVELS.index(min_level.upper()) :])
            levels = f" AND upper(level) IN ({wanted})"
        query = (
            "SELECT log_time, entity, level, text FROM text_logs "
            f"WHERE run_id = '{_run(run_id)}' AND log_time BETWEEN '{_sql_time(start)}' AND '{_sql_time(end)}'"
            f"{levels} ORDER BY log_time LIMIT {limit}"
        )
        async with connect(ctx) as api:
            return bounded(_rows(await api.call("POST", "/v1/sql", body={"query": query})))

    @server.tool(annotations=READ)
    async def scalar_series(
        ctx: Context[Any, Any, Any],
        run_id: RunId,
        entity: Annotated[str, Field(description="the entity path, e.g. /battery", max_length=512)],
        start: Annotated[str | None, Field(description="from, ISO-8601 (default: the run's start)")] = None,
        end: Annotated[str | None, Field(description="to, ISO-8601 (default: the run's end)")] = None,
        points: Annotated[int, Field(ge=2, le=1000, description="most points: averaged in time buckets")] = 200,
    ) -> dict[str, Any]:
        """A scalar signal of a run (Scalars) over time, downsampled to at most `points` buckets
        (each its mean, min and max), per instance (index in a logged list)."""
        if "'" in entity or not entity.startswith("/"):
            raise ToolError(f"entity {entity!r} is not an entity path such as /battery")
        window = f"run_id = '{_run(run_id)}' AND entity = '{entity}'"
        if start is not None:
            window += f" AND log_time >= '{_sql_time(_instant(start))}'"
        if end is not None:
            window += f" AND log_time <= '{_sql_time(_instant(end))}'"
        query = (
            f"WITH s AS (SELECT log_time, instance, value FROM scalars WHERE {window}), "
            "r AS (SELECT min(log_time) AS t0, greatest(epoch_ns(max(log_time)) - epoch_ns(min(log_time)), 1) AS span "
            "FROM s) "
            f"SELECT least(floor((epoch_ns(s.log_time) - epoch_ns(r.t0)) * {points} / r.span), {points - 1}) "
            "AS bucket, instance, min(s.log_time) AS t, avg(value) AS mean, min(value) AS lo, max(value) AS hi, "
            "count(*) AS n FROM s, r GROUP BY ALL ORDER BY instance, bucket"
        )
        async with connect(ctx) as api:
            return bounded(_rows(await api.call("POST", "/v1/sql", body={"query": query})), max_items=2000)

    @server.tool(annotations=READ)
    async def sql(
        ctx: Context[Any, Any, Any],
        query: Annotated[str, Field(description="one read-only SELECT (DuckDB dialect)", max_length=20_000)],
        max_rows: Annotated[int, Field(ge=1, le=500)] = 100,
    ) -> dict[str, Any]:
        """Read-only SQL over the fleet: tables runs, robots, run_entities, run_timelines,
        run_metrics, events, run_tags, and the telemetry scalars, text_logs, transforms (each with
        run_id, robot_id, date, entity, log_time). Filter on robot_id and date to read less."""
        async with connect(ctx) as api:
            answer = _rows(await api.call("POST", "/v1/sql", body={"query": query}))
        return bounded(answer, max_items=max_rows)

    @server.tool(annotations=READ)
    async def viewer_link(
        ctx: Context[Any, Any, Any],
        run_id: RunId,
        start: Annotated[str | None, Field(description="window start, ISO-8601 (on log_time)")] = None,
        end: Annotated[str | None, Field(description="window end, ISO-8601")] = None,
        include: Annotated[list[str] | None, Field(description="entities to keep: /a/b or /a/**")] = None,
        expires_in_s: Annotated[int, Field(ge=60, le=7 * 86400)] = 3600,
    ) -> dict[str, Any]:
        """A signed, expiring link to a run (or a time window of it, some entities only) that the
        Rerun viewer opens: give it to the person (`rerun URL`, or paste it in the web viewer)."""
        params: dict[str, Any] = {"include": include, "expires_in": expires_in_s}
        if start is not None or end is not None:
            params["timeline"] = "log_time"
            params["start"] = _iso(_instant(start)) if start else None
            params["end"] = _iso(_instant(end)) if end else None
        async with connect(ctx) as api:
            link = await api.call("POST", f"/v1/runs/{_run(run_id)}/links", params=params)
        return {**link, "open_with": f"rerun '{link['url']}'"}

    @server.tool(annotations=WRITE)
    async def tag_run(
        ctx: Context[Any, Any, Any],
        run_id: RunId,
        tags: Annotated[list[str], Field(min_length=1, max_length=20, description="tags to add, e.g. night-shift")],
    ) -> dict[str, Any]:
        """Add tags to a run (needs a write token); who added each is kept."""
        async with connect(ctx) as api:
            return bounded(await api.call("POST", f"/v1/runs/{_run(run_id)}/tags", body={"tags": tags}))

    @server.tool(annotations=WRITE)
    async def annotate_run(
        ctx: Context[Any, Any, Any],
        run_id: RunId,
        start: Annotated[str, Field(description="ISO-8601 on log_time")],
        end: Annotated[str | None, Field(description="ISO-8601; none: an instant")] = None,
        label: Annotated[str, Field(max_length=512)] = "",
        note: Annotated[str, Field(max_length=4096)] = "",
        severity: Annotated[str, Field(description="info | warn | error")] = "info",
    ) -> dict[str, Any]:
        """Mark a time range of a run as an event (a person's annotation, needs a write token)."""
        body = {
            "timeline": "log_time",
            "start": _iso(_instant(start)),
            "end": _iso(_instant(end)) if end else None,
            "label": label,
            "note": note,
            "severity": severity,
        }
        async with connect(ctx) as api:
            return bounded(await api.call("POST", f"/v1/runs/{_run(run_id)}/events", body=body))

    @server.tool(annotations=WRITE)
    async def request_pull(
        ctx: Context[Any, Any, Any],
        run_id: RunId,
        start: Annotated[str | None, Field(description="window start, ISO-8601 (on log_time)")] = None,
        end: Annotated[str | None, Field(description="window end, ISO-8601")] = None,
        include: Annotated[list[str] | None, Field(description="entities: /a/b or /a/**")] = None,
    ) -> dict[str, Any]:
        """Ask the run's robot to send (part of) its full recording home (needs a write token); its
        agent picks the pull up when it next polls."""
        body: dict[str, Any] = {"include": include or []}
        if start is not None or end is not None:
            body |= {"timeline": "log_time", "start": _iso(_instant(start)) if start else None}
            body["end"] = _iso(_instant(end)) if end else None
        async with connect(ctx) as api:
            return bounded(await api.call("POST", f"/v1/runs/{_run(run_id)}/pull", body=body))

    @server.resource("fleet://runs/{run_id}", mime_type="application/json")
    async def run_summary(run_id: str, ctx: Context[Any, Any, Any]) -> dict[str, Any]:
        """A run's summary: robot, application, times, tier, size, metrics, tags and event counts."""
        async with connect(ctx) as api:
            run = await api.call("GET", f"/v1/runs/{_run(run_id)}")
        kept = ("id", "robot_id", "application_id", "date", "status", "tier", "started_at", "ended_at")
        summary = {k: run.get(k) for k in kept}
        summary |= {k: run.get(k) for k in ("bytes", "chunks", "metrics", "tags", "event_counts") if k in run}
        return bounded(summary)

    return server


def _run(run_id: str) -> str:
    if not is_id(run_id):
        raise ToolError(f"{run_id!r} is not a run id: ids are letters, digits, '.', '_' and '-'")
    return run_id


def _instant(text: str) -> dt.datetime:
    """An ISO-8601 time (a zone-less one is UTC)."""
    try:
        moment = dt.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ToolError(f"{text!r} is not an ISO-8601 time such as 2026-11-30T12:00:00Z") from None
    return moment if moment.tzinfo else moment.replace(tzinfo=dt.UTC)


def _sql_time(moment: dt.datetime) -> str:
    """As the telemetry's `log_time` (UTC, no zone) compares in SQL."""
    return moment.astimezone(dt.UTC).replace(tzinfo=None).isoformat(sep=" ")


def _iso(moment: dt.datetime) -> str:
    return moment.astimezone(dt.UTC).isoformat().replace("+00:00", "Z")


def _rows(answer: dict[str, Any]) -> dict[str, Any]:
    """The SQL answer as a list of {column: value}."""
    names = [c["name"] for c in answer.get("columns", [])]
    return {"rows": [dict(zip(names, row, strict=True)) for row in answer.get("rows", [])]}
