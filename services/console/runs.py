"""The console's runs table (`GET /console/runs`): the filters of `GET /v1/runs` (robot,
application, since, until, status, tier, entity, property NAME.FIELD=VALUE, metric `distance_m>100`,
tag, event), sort (a metric's too: `metric.NAME`) and cursor paging,
all as query parameters, so a table's URL can be kept and shared."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any
from urllib.parse import urlencode

from fastapi import Request
from fastapi.responses import HTMLResponse
from starlette.datastructures import QueryParams

from core.errors import BadParameterError, InvalidArgumentError
from services.console.web import PREFIX, Viewer, console_router, render
from services.runs import service
from services.runs.service import RunFilter, parse_properties, parse_time

router = console_router()

DEFAULT_LIMIT = 50
LIMITS = (25, 50, 100, 250, 1000)
# Columns whose header sorts the table: column -> the sort key, and which way a first click sorts.
SORTABLE = {"run": ("id", ""), "started": ("started_at", "-"), "size": ("bytes", "-")}


@dataclass(frozen=True)
class RunsQuery:
    """The table's query parameters as given (blank fields dropped): what its links carry."""

    robot: list[str] = field(default_factory=list)
    application: list[str] = field(default_factory=list)
    since: str = ""
    until: str = ""
    status: str = ""
    tier: str = ""
    entity: list[str] = field(default_factory=list)
    property: list[str] = field(default_factory=list)
    metric: list[str] = field(default_factory=list)  # `distance_m>100`, as GET /v1/runs takes it
    tag: list[str] = field(default_factory=list)
    event: list[str] = field(default_factory=list)
    sort: str = "-started_at"
    limit: str = str(DEFAULT_LIMIT)
    cursor: str = ""

    @classmethod
    def of(cls, params: QueryParams) -> RunsQuery:
        def many(name: str) -> list[str]:
            return [v.strip() for v in params.getlist(name) if v.strip()]

        def one(name: str, default: str = "") -> str:
            return (params.get(name) or "").strip() or default

        # robot ids hold no comma or space: one box takes several ("robot-a, robot-b")
        robots = [r for value in many("robot") for r in value.replace(",", " ").split()]
        return cls(
            robot=robots,
            application=many("application"),
            since=one("since"),
            until=one("until"),
            status=one("status"),
            tier=one("tier"),
            entity=many("entity"),
            property=many("property"),
            metric=many("metric"),
            tag=many("tag"),
            event=many("event"),
            sort=one("sort", "-started_at"),
            limit=one("limit", str(DEFAULT_LIMIT)),
            cursor=one("cursor"),
        )

    def run_filter(self) -> RunFilter:
        """The service's filter; BadParameterError naming what is wrong (a bad date, an unknown tier)."""
        try:
            limit = int(self.limit)
        except ValueError:
            raise BadParameterError("limit", f"{self.limit!r} is not a number from 1 to {service.MAX_LIMIT}") from None
        return RunFilter(
            robot=self.robot,
            application=self.application,
            since=parse_time("since", self.since or None),
            until=parse_time("until", self.until or None),
            status=self.status or None,
            tier=self.tier or None,
            entity=self.entity,
            properties=parse_properties(self.property),
            metric=self.metric,
            tag=self.tag,
            event=self.event,
            sort=self.sort,
            limit=limit,
            cursor=self.cursor or None,
        )

    def pairs(self) -> list[tuple[str, str]]:
        """The query string's parameters, blank and default ones left out."""
        out: list[tuple[str, str]] = [("robot", ",".join(self.robot))] if self.robot else []
        out += [("application", v) for v in self.application]
        out += [(name, value) for name, value in (("since", self.since), ("until", self.until)) if value]
        out += [(name, value) for name, value in (("status", self.status), ("tier", self.tier)) if value]
        out += [("entity", v) for v in self.entity] + [("property", v) for v in self.property]
        out += [(name, v) for name, values in self.corpus_filters() for v in values]
        if self.sort != "-started_at":
            out.append(("sort", self.sort))
        if self.limit != str(DEFAULT_LIMIT):
            out.append(("limit", self.limit))
        if self.cursor:
            out.append(("cursor", self.cursor))
        return out

    def corpus_filters(self) -> tuple[tuple[str, list[str]], ...]:
        return (("metric", self.metric), ("tag", self.tag), ("event", self.event))

    def href(self, **changes: Any) -> str:
        """This table's URL with some parameters changed (a new sort, the next page's cursor)."""
        query = urlencode(replace(self, **changes).pairs())
        return f"{PREFIX}/runs" + (f"?{query}" if query else "")


def sort_links(query: RunsQuery) -> dict[str, dict[str, str]]:
    """For each sortable column: the link its header points to (first page, same filters) and
    whether the table is sorted by it now (asc, desc or "")."""
    links = {}
    for column, (key, first) in SORTABLE.items():
        if query.sort == key:
            state, target = "asc", f"-{key}"
        elif query.sort == f"-{key}":
            state, target = "desc", key
        else:
            state, target = "", f"{first}{key}"
        links[column] = {"href": query.href(sort=target, cursor=""), "state": state}
    return links


@router.get("/runs")
def runs_page(request: Request, principal: Viewer) -> HTMLResponse:
    query = RunsQuery.of(request.query_params)
    problem, status = None, 200
    try:
        answer = service.runs_answer(request.app.state.catalog, query.run_filter())
    except InvalidArgumentError as exc:  # the filter's own words: what is wrong and what would do
        answer, problem, status = {"runs": [], "next_cursor": None}, exc.message, 400
    custom = query.limit if query.limit.isdigit() and len(query.limit) <= 4 else ""  # a limit given in the URL
    limits = sorted({*LIMITS, int(custom)} if custom and 1 <= int(custom) <= service.MAX_LIMIT else set(LIMITS))
    return render(
        request,
        "runs.html",
        principal,
        status=status,
        q=query,
        runs=answer["runs"],
        next_href=query.href(cursor=answer["next_cursor"]) if answer["next_cursor"] else None,
        first_href=query.href(cursor="") if query.cursor else None,
        sorts=sort_links(query),
        statuses=service.STATUSES,
        tiers=service.TIERS,
        limits=limits,
        problem=problem,
    )
