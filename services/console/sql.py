"""The console's SQL page (a query box over the same workers and rate limit as `POST /v1/sql`, the
answer as a table, a chart for a two-column answer, CSV and Parquet downloads) and the dashboards
of saved queries, each computed again at every look."""

from __future__ import annotations

from typing import Annotated
from urllib.parse import urlencode

from fastapi import Query, Request
from fastapi.responses import RedirectResponse, Response
from markupsafe import Markup

from catalog.saved_queries import CHARTS
from core.errors import FleetError, InvalidArgumentError, UnavailableError
from services.analytics import saved
from services.analytics.saved import Chart
from services.analytics.service import FORMATS, Analytics, encode
from services.auth.depends import rate_limits
from services.auth.scopes import Principal, Scope
from services.console import charts
from services.console.web import PREFIX, Form, Viewer, console_router, render

router = console_router()
DOWNLOADS = ("csv", "parquet")
CHART_CHOICES = ("auto", *CHARTS)


def analytics_of(request: Request) -> Analytics:
    ctx: Analytics | None = request.app.state.analytics
    if ctx is None:
        raise UnavailableError(
            "this depot serves no SQL (it runs without its analytics side): use a full `fleet serve`"
        )
    return ctx


def limited_sql(request: Request, principal: Principal) -> None:
    """One SQL query against the token's rate, as `POST /v1/sql` counts it."""
    rate_limits(request).hit("sql", principal)


def draw(chart: Chart, title: str = "") -> Markup:
    """A chart as SVG: a line over numbers or times, else bars."""
    if chart.kind == "line":
        return charts.lines(
            [charts.Series(chart.y_name, chart.points)],
            x_label=chart.x_name,
            x_format="time_ns" if chart.x_format == "time_ns" else "number",
            title=title or f"{chart.y_name} by {chart.x_name}",
        )
    return charts.bars(chart.labels, chart.ys, title=title or f"{chart.y_name} by {chart.x_name}")


def sql_link(text: str, **more: str) -> str:
    return f"{PREFIX}/sql?{urlencode({'q': text, **more})}"


def _page(
    request: Request,
    principal: Principal,
    text: str,
    *,
    answer: saved.Answer | None = None,
    problem: FleetError | None = None,
    save_problem: FleetError | None = None,
    name: str = "",
    chart: str = "auto",
) -> Response:
    failed = problem or save_problem
    return render(
        request,
        "sql.html",
        principal,
        status=failed.http_status() if failed is not None else 200,
        q=text,
        example=saved.EXAMPLE,
        answer=answer,
        problem=problem,
        save_problem=save_problem,
        save_name=name,
        chart_kind=chart,
        chart_choices=CHART_CHOICES,
        max_shown=saved.MAX_SHOWN,
        tables=saved.tables(),
        downloads={fmt: f"{PREFIX}/sql/download?{urlencode({'q': text, 'format': fmt})}" for fmt in DOWNLOADS},
        draw=draw,
    )


@router.get("/sql")
def sql_page(request: Request, principal: Viewer, q: Annotated[str, Query()] = "") -> Response:
    """The query box; with `?q=` the query runs and its answer is shown (so answers are linkable)."""
    if not q.strip():
        return _page(request, principal, "")
    ctx = analytics_of(request)
    try:
        limited_sql(request, principal)
        answer = saved.answer(saved.run_sql(ctx, q))
    except FleetError as exc:  # a bad query is the page with its message (400), not an error page
        return _page(request, principal, q, problem=exc)
    return _page(request, principal, q, answer=answer)


@router.get("/sql/download")
def sql_download(
    request: Request,
    principal: Viewer,
    q: Annotated[str, Query()] = "",
    fmt: Annotated[str, Query(alias="format")] = "csv",
) -> Response:
    """A query's whole answer as CSV or Parquet, saved by the browser as a file."""
    if fmt not in DOWNLOADS:
        raise InvalidArgumentError(f"format {fmt!r} is not one of {', '.join(DOWNLOADS)}")
    ctx = analytics_of(request)
    limited_sql(request, principal)
    table = saved.run_sql(ctx, q)
    return Response(
        encode(table, fmt),
        media_type=FORMATS[fmt],
        headers={
            "content-disposition": f'attachment; filename="query.{fmt}"',
            "x-row-count": str(table.num_rows),
        },
    )


@router.post("/sql/save")
def sql_save(request: Request, principal: Viewer, form: Form) -> Response:
    """Save the query as a dashboard chart (write scope): it must run, and its name be free."""
    principal.require(Scope.WRITE)
    text = str(form.get("q") or "")
    name = str(form.get("name") or "")
    chart = str(form.get("chart") or "auto")
    ctx = analytics_of(request)
    try:
        limited_sql(request, principal)
        answer = saved.answer(saved.run_sql(ctx, text))  # a query that fails is not saved
    except FleetError as exc:
        return _page(request, principal, text, problem=exc, name=name, chart=chart)
    if chart == "auto":
        chart = answer.chart.kind if answer.chart is not None else "table"
    try:
        record = saved.save(ctx, name, text, chart, principal.subject)
    except FleetError as exc:
        return _page(request, principal, text, answer=answer, save_problem=exc, name=name, chart=chart)
    return RedirectResponse(f"{PREFIX}/dashboards#{record.id}", status_code=303)


@router.get("/dashboards")
def dashboards(request: Request, principal: Viewer) -> Response:
    """Every saved query's answer now, drawn as its chart."""
    ctx = analytics_of(request)
    drawn = saved.run_all(ctx, saved.saved(ctx), lambda: limited_sql(request, principal))
    return render(request, "dashboards.html", principal, drawn=drawn, draw=draw, sql_link=sql_link)


@router.get("/dashboards/{query_id}/chart")
def dashboard_chart(request: Request, principal: Viewer, query_id: str) -> Response:
    """One saved query's chart now (what the dashboards page refreshes every minute)."""
    ctx = analytics_of(request)
    one = saved.run_one(ctx, saved.one(ctx, query_id), lambda: limited_sql(request, principal))
    return render(request, "dashboard_chart.html", principal, d=one, draw=draw)


@router.post("/dashboards/{query_id}/delete")
def dashboard_delete(request: Request, principal: Viewer, _: Form, query_id: str) -> Response:
    principal.require(Scope.WRITE)
    saved.delete(analytics_of(request), query_id)
    return RedirectResponse(f"{PREFIX}/dashboards", status_code=303)
