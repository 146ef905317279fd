"""A run's page (`/console/runs/{run}`): what it is, where it is and what retention does next, its
entities, coverage (with its events marked), events, metrics and tags, scalar plots and text logs, the
`rerun` command with a signed link, and its actions by scope (pin, restore, promote, pull, delete;
tags and annotations in run_edits; a filtered download by signed link)."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from catalog.edge import PullAsk
from core.errors import BadParameterError, FleetError, UnavailableError
from core.states import Tier
from services.analytics import run_views as analytics_views
from services.auth.depends import actor
from services.auth.scopes import Principal, Scope
from services.console import charts
from services.console.run_corpus import corpus_context
from services.console.web import PREFIX, Form, Viewer, console_router, render
from services.edge import pulls
from services.retention import service as retention_service
from services.runs import links
from services.runs import run_views as runs_views
from services.runs import service as runs_service
from services.runs.download import EntityFilter, window_from_query

router = console_router()

# What an action did, shown on the page it leads back to (fixed texts: nothing from the URL is shown).
NOTICES = {
    "pinned": "Pinned: retention will not delete this run while it stays pinned.",
    "unpinned": "Unpinned: the run's retention policy applies again.",
    "restore": "Restore asked for: the run is readable again once its state says restored.",
    "promoted": "Promoted: the run is sealed into the warm tier.",
    "pull": "Pull queued: the robot's agent sends the run's missing chunks when it next polls.",
    "pull-pending": "The same pull was queued already: nothing new was asked of the robot.",
    "deleted": "Deleted: the run's objects are gone; its tombstone stays.",
    "tagged": "Tagged: the run's tags are listed below.",
    "untagged": "Tag removed.",
    "annotated": "Annotated: your event is in the run's events.",
}


@dataclass(frozen=True)
class TreeNode:
    path: str
    name: str
    depth: int
    entity: dict[str, Any] | None  # None for a path that only holds other entities


def entity_tree(entities: list[dict[str, Any]]) -> list[TreeNode]:
    """The run's entities as an indented tree: every path with its parents, in path order."""
    by_path = {e["path"]: e for e in entities}
    paths: set[str] = set()
    for path in by_path:
        parts = [p for p in path.split("/") if p]
        for i in range(1, len(parts) + 1):
            paths.add("/" + "/".join(parts[:i]))
        if not parts:
            paths.add("/")
    nodes = []
    for path in sorted(paths, key=lambda p: [part for part in p.split("/") if part]):
        parts = [p for p in path.split("/") if p]
        nodes.append(TreeNode(path, parts[-1] if parts else "/", max(len(parts) - 1, 0), by_path.get(path)))
    return nodes


def patterns(text: str | None) -> list[str]:
    """Entity patterns typed in one field, separated by spaces, commas or new lines."""
    return [p for p in re.split(r"[\s,]+", text or "") if p]


def _blank(value: Any) -> str | None:
    text = str(value or "").strip()
    return text or None


def signed_link(request: Request, principal: Principal, run_id: str, params: list[tuple[str, str]], base: str) -> str:
    state = request.app.state
    settings = state.settings
    link = links.recording_link(
        state.auth,
        principal,
        links.RunLookup(state.ingest, state.catalog),
        run_id,
        params,
        links.lifetime(None, settings.link_ttl_s),
        base,
    )
    return str(link["url"])


def public_base(request: Request) -> str:
    """The depot's address people reach it by, for links that leave the browser (a `rerun`
    command): never taken from a Host header that is not one of the depot's (`links.public_base`)."""
    return links.request_base(request)


def _timeline_types(answer: dict[str, Any]) -> dict[str, str]:
    return {t["name"]: t["type"] for t in answer["timelines"]}


def _views(request: Request, answer: dict[str, Any], x: str | None) -> analytics_views.RunViews:
    state = request.app.state
    types = _timeline_types(answer)
    if answer["tier"] == Tier.HOT:
        if state.ingest is None:
            return analytics_views.RunViews("hot run", note="this node holds no hot runs")
        return analytics_views.hot_views(state.ingest, answer["id"], types, x)
    if answer["tier"] == Tier.DELETED:
        return analytics_views.RunViews("analytics tables", note="the run is deleted: its tables went with it")
    try:
        return analytics_views.sealed_views(state.catalog, state.node.tiers.warm, answer["id"], types, x)
    except FleetError as exc:  # the store did not answer: the rest of the page still shows
        return analytics_views.RunViews(
            "analytics tables", note=f"the run's analytics tables cannot be read: {exc.message}"
        )


def _next_step(request: Request, answer: dict[str, Any]) -> runs_views.NextStep:
    retention = request.app.state.retention
    if answer["tier"] == Tier.HOT and retention is not None:
        for coming in retention_service.upcoming(retention):
            if coming["run"] == answer["id"]:
                return runs_views.NextStep("promote", coming["at"], coming["reason"])
        if retention.ingest is not None and retention.ingest.hot_run(answer["id"]) is not None:
            return runs_views.NextStep("promote", None, "closed and due: the next promotion pass seals it")
    return runs_views.next_step(answer, retention.policies if retention is not None else None)


def run_page(
    request: Request,
    principal: Principal,
    run_id: str,
    *,
    notice: str | None = None,
    problem: FleetError | None = None,
    x: str | None = None,
    asked: dict[str, str] | None = None,
) -> HTMLResponse:
    """The page; with `problem`, that error shown on it with its status."""
    state = request.app.state
    retention = state.retention
    policies = retention.policies if retention else None
    answer = runs_service.run_answer(
        state.catalog, run_id, policies, runs_service.hot_lookup(state.ingest, state.node.default_robot)
    )
    deleted = answer["tier"] == Tier.DELETED
    views = _views(request, answer, x)
    cover, cover_problem = runs_views.run_coverage(
        state.ingest,
        state.catalog,
        state.node.tiers.warm,
        run_id,
        views.x.removeprefix("timeline_") if views.x else None,
    )
    command_url = None if deleted else signed_link(request, principal, run_id, [], public_base(request))
    plots = [
        (
            plot.entity,
            charts.lines(
                [charts.Series(line.name, line.points) for line in plot.lines],
                x_label=plot.x,
                x_format="time_ns" if views.x_type == "timestamp" else "number",
                title=f"{plot.entity} over {plot.x}",
            ),
            sum(line.logged for line in plot.lines),
        )
        for plot in views.plots
    ]
    corpus = corpus_context(request, principal, run_id, cover)
    coverage_chart = (
        charts.coverage(cover.rows, cover.lo, cover.hi, marks=corpus["event_marks"]) if cover is not None else None
    )
    return render(
        request,
        "run.html",
        principal,
        status=problem.http_status() if problem is not None else 200,
        run=answer,
        tree=entity_tree(answer["entities"]),
        views=views,
        plots=plots,
        coverage=cover,
        coverage_chart=coverage_chart,
        coverage_problem=cover_problem,
        next_step=_next_step(request, answer),
        command_url=command_url,
        notice=notice,
        problem=problem,
        asked={**dict.fromkeys(("include", "exclude", "timeline", "start", "end"), ""), **(asked or {})},
        **corpus,
    )


@router.get("/runs/{run_id}")
def run(
    request: Request,
    run_id: str,
    principal: Viewer,
    done: Annotated[str | None, Query()] = None,
    x: Annotated[str | None, Query()] = None,
) -> HTMLResponse:
    return run_page(request, principal, run_id, notice=NOTICES.get(done or ""), x=x)


# --- actions --------------------------------------------------------------------------------------


def act(request: Request, principal: Principal, run_id: str, scope: Scope, work: Callable[[], str]) -> Response:
    """Check the scope again, do the action, and go back to the run's page saying what happened;
    a refusal or failure is shown on the run's page with its status."""
    try:
        principal.require(scope)
        done = work()
    except FleetError as exc:
        return run_page(request, principal, run_id, problem=exc)
    return RedirectResponse(f"{PREFIX}/runs/{quote(run_id, safe='')}?done={done}", status_code=303)


def _retention(request: Request) -> retention_service.Retention:
    found: retention_service.Retention | None = request.app.state.retention
    if found is None:
        raise UnavailableError("this node runs no retention: pin, restore, promote and delete on a node that does")
    return found


@router.post("/runs/{run_id}/pin")
def pin(request: Request, run_id: str, principal: Viewer, _: Form) -> Response:
    def work() -> str:
        retention_service.set_pinned(_retention(request), run_id, True, actor(request, principal))
        return "pinned"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/unpin")
def unpin(request: Request, run_id: str, principal: Viewer, _: Form) -> Response:
    def work() -> str:
        retention_service.set_pinned(_retention(request), run_id, False, actor(request, principal))
        return "unpinned"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/restore")
def restore(request: Request, run_id: str, principal: Viewer, _: Form) -> Response:
    def work() -> str:
        retention_service.request_restore(_retention(request), run_id, actor(request, principal))
        return "restore"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/promote")
def promote(request: Request, run_id: str, principal: Viewer, _: Form) -> Response:
    def work() -> str:
        retention_service.promote_now(_retention(request), run_id, actor(request, principal))
        return "promoted"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/pull")
def pull(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        edge = getattr(request.app.state, "edge", None)
        if edge is None:
            raise UnavailableError("this node keeps no pulls (it has no catalog of robots' runs): ask another node")
        ask = PullAsk(
            run_id,
            patterns(str(form.get("include") or "")),
            patterns(str(form.get("exclude") or "")),
            _blank(form.get("timeline")),
            _blank(form.get("start")),
            _blank(form.get("end")),
        )
        _, created = pulls.request_pull(edge, ask, actor(request, principal))
        return "pull" if created else "pull-pending"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/delete")
def delete(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        typed = str(form.get("confirm") or "").strip()
        if typed != run_id:
            raise BadParameterError("confirm", f"type the run's id ({run_id}) to confirm: deleting cannot be undone")
        retention_service.delete_now(_retention(request), run_id, actor(request, principal))
        return "deleted"

    return act(request, principal, run_id, Scope.ADMIN, work)


@router.get("/runs/{run_id}/download")
def download(
    request: Request,
    run_id: str,
    principal: Viewer,
    include: Annotated[str | None, Query()] = None,
    exclude: Annotated[str | None, Query()] = None,
    timeline: Annotated[str | None, Query()] = None,
    start: Annotated[str | None, Query()] = None,
    end: Annotated[str | None, Query()] = None,
) -> Response:
    """The run (filtered) by a signed link: the browser downloads it without sending a header."""
    asked = {
        k: v or ""
        for k, v in (("include", include), ("exclude", exclude), ("timeline", timeline), ("start", start), ("end", end))
    }
    try:
        answer = runs_service.run_answer(
            request.app.state.catalog,
            run_id,
            None,
            runs_service.hot_lookup(request.app.state.ingest, request.app.state.node.default_robot),
        )
        keep, drop = patterns(include), patterns(exclude)
        EntityFilter(keep, drop)  # checked here: a bad pattern is shown on the page, not downloaded as JSON
        window = (_blank(timeline), _blank(start), _blank(end))
        window_from_query(_timeline_types(answer), *window, latest_at=True)
        params = [("include", p) for p in keep] + [("exclude", p) for p in drop]
        params += [(k, v) for k, v in zip(("timeline", "start", "end"), window, strict=True) if v is not None]
        url = signed_link(request, principal, run_id, params, "")  # the redirect stays on this origin
    except FleetError as exc:
        return run_page(request, principal, run_id, problem=exc, asked=asked)
    return RedirectResponse(url, status_code=303)
