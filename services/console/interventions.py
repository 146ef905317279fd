"""The built-in dashboard "distance between interventions" (`GET /console/dashboards/interventions`):
per ISO week of a run's start and per software version, the distance driven divided by the
interventions, from the runs' metrics. It is one SQL query over `runs` and `run_metrics`, run by the
same workers as `POST /v1/sql` at every look (so it follows the runs sealed since), and shown on the
page so its numbers can be checked there. The metrics' names are query parameters."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Query, Request
from fastapi.responses import Response
from markupsafe import Markup

from core.errors import BadParameterError, FleetError
from services.analytics import saved
from services.console import charts
from services.console.sql import analytics_of, limited_sql, sql_link
from services.console.web import Viewer, console_router, render

router = console_router()

METRIC_NAME = re.compile(r"[A-Za-z0-9_.:\-]{1,256}")  # what a rules file names a metric (no quote)
DEFAULTS = {"distance": "distance_m", "interventions": "interventions", "version": "sw_version"}
COLUMNS = ("iso_week", "sw_version", "runs", "distance", "interventions", "distance_per_intervention")


@dataclass(frozen=True)
class Metrics:
    """The metrics the dashboard divides: a distance, a count of interventions (an `event_count`
    metric), and a software version (a `property` metric, text or number)."""

    distance: str = DEFAULTS["distance"]
    interventions: str = DEFAULTS["interventions"]
    version: str = DEFAULTS["version"]

    def check(self) -> Metrics:
        given = (("distance", self.distance), ("interventions", self.interventions), ("version", self.version))
        for name, value in given:
            if not METRIC_NAME.fullmatch(value):
                raise BadParameterError(name, f"{value[:60]!r} is not a metric name (letters, digits, _ . : -)")
        return self


def dashboard_sql(metrics: Metrics) -> str:
    """The query, as an analyst would write it for `POST /v1/sql` (names checked: no quote in them)."""
    return f"""\
-- Distance between interventions per ISO week of the run's start and per software version.
-- Metrics: distance '{metrics.distance}', interventions '{metrics.interventions}', version '{metrics.version}'.
WITH per_run AS (
  SELECT strftime(timezone('UTC', r.started_at), '%G-W%V') AS iso_week,
         coalesce(v.text_value, CAST(v.value AS VARCHAR), '(none)') AS sw_version,
         d.value AS distance,
         i.value AS interventions
  FROM runs r
  JOIN run_metrics d ON d.run_id = r.id AND d.name = '{metrics.distance}'
  LEFT JOIN run_metrics i ON i.run_id = r.id AND i.name = '{metrics.interventions}'
  LEFT JOIN run_metrics v ON v.run_id = r.id AND v.name = '{metrics.version}'
  WHERE r.started_at IS NOT NULL
)
SELECT iso_week, sw_version, count(*) AS runs,
       sum(distance) AS distance,
       sum(interventions) AS interventions,
       sum(distance) / nullif(sum(interventions), 0) AS distance_per_intervention
FROM per_run
GROUP BY iso_week, sw_version
ORDER BY iso_week, sw_version"""


def rows_of(request: Request, text: str) -> list[dict[str, Any]]:
    table = saved.run_sql(analytics_of(request), text)
    return [dict(zip(COLUMNS, row.values(), strict=True)) for row in table.to_pylist()]


def chart(rows: list[dict[str, Any]]) -> Markup:
    """One bar per week and version that had an intervention."""
    shown = [r for r in rows if r["distance_per_intervention"] is not None]
    return charts.bars(
        [f"{r['iso_week']} · {r['sw_version']}" for r in shown],
        [float(r["distance_per_intervention"]) for r in shown],
        title="distance per intervention",
    )


@router.get("/dashboards/interventions")
def interventions(
    request: Request,
    principal: Viewer,
    distance: Annotated[str, Query()] = DEFAULTS["distance"],
    interventions: Annotated[str, Query()] = DEFAULTS["interventions"],
    version: Annotated[str, Query()] = DEFAULTS["version"],
) -> Response:
    metrics = Metrics(distance.strip(), interventions.strip(), version.strip())
    rows: list[dict[str, Any]] = []
    problem: FleetError | None = None
    text = ""
    try:
        text = dashboard_sql(metrics.check())
        limited_sql(request, principal)
        rows = rows_of(request, text)
    except FleetError as exc:  # a bad name, or the SQL side cannot answer now: the page says so
        problem = exc
    return render(
        request,
        "interventions.html",
        principal,
        status=problem.http_status() if problem is not None else 200,
        metrics=metrics,
        sql=text,
        sql_href=sql_link(text) if text else "",
        rows=rows,
        chart=chart(rows) if rows else None,
        problem=problem,
    )
