"""The console's Imports pages ([mcap.md](../../docs/mcap.md)): every upload, RRD or MCAP, as
`GET /v1/imports` lists it (`services.imports.records`):

- `/console/imports`: imports newest first, filtered by state, kind and robot (query parameters, so
  a view can be kept and shared), a page at a time (`before`, as the REST route pages); each with its
  file, size, robot, runs (linked to their pages), new chunks, when, and why it failed;
- `/console/imports/ID`: one import with every field `GET /v1/imports/ID` answers; a failed MCAP
  import whose original is in quarantine has a Retry button (`write` scope: `POST
  /console/imports/ID/retry`, the same `Importer.retry` as `POST /v1/imports/ID/retry`) and, for an
  admin, a link to download the original (`/console/imports/ID/original`, the same download as
  `GET /v1/imports/ID/original`).

An unknown import is the console's 404 page; a bad filter is said on the list."""

from __future__ import annotations

import asyncio
from typing import Any
from urllib.parse import quote, urlencode

from fastapi import Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from catalog import imports as rows
from core.errors import BadParameterError, FleetError, UnavailableError
from services.auth.scopes import Principal, Scope
from services.console.web import PREFIX, Form, Viewer, console_router, render
from services.imports import records
from services.imports import rest as imports_rest

router = console_router()
PAGE = 50  # imports on a page of the list
FILTERS = ("state", "kind", "robot")
# What a retry did, shown on the import's page it leads back to (fixed texts: nothing from the URL).
NOTICES = {
    "retried": "Retried: the original was converted again and filed.",
    "retry-failed": "Retried, and it failed again: the reason is below.",
}


def import_href(import_id: str) -> str:
    return f"{PREFIX}/imports/{quote(import_id, safe='')}"


def run_href(run_id: str) -> str:
    return f"{PREFIX}/runs/{quote(run_id, safe='')}"


def asked_of(request: Request) -> dict[str, str]:
    """The list's filters and page (`before`) as the URL gives them; blank ones are ''."""
    return {name: (request.query_params.get(name) or "").strip() for name in (*FILTERS, "before")}


def list_href(asked: dict[str, str], **changes: str) -> str:
    """The list's URL with some parameters changed (a filter, the next page's `before`)."""
    given = {**asked, **changes}
    query = urlencode([(name, given[name]) for name in (*FILTERS, "before") if given.get(name)])
    return f"{PREFIX}/imports" + (f"?{query}" if query else "")


@router.get("/imports")
def imports_page(request: Request, principal: Viewer) -> HTMLResponse:
    asked = asked_of(request)
    problem, status = None, 200
    try:
        answer = records.listed(
            request.app.state.catalog,
            state=asked["state"] or None,
            kind=asked["kind"] or None,
            robot=asked["robot"] or None,
            limit=PAGE,
            before=asked["before"] or None,
        )
    except BadParameterError as exc:  # a state or kind that is none: the page says so
        answer, problem, status = {"imports": []}, exc.message, exc.http_status()
    next_before = answer.get("next_before")
    return render(
        request,
        "imports.html",
        principal,
        status=status,
        asked=asked,
        imports=answer["imports"],
        states=rows.STATES,
        kinds=rows.KINDS,
        next_href=list_href(asked, before=next_before) if next_before else None,
        first_href=list_href(asked, before="") if asked["before"] else None,
        list_href=list_href,
        import_href=import_href,
        run_href=run_href,
        problem=problem,
    )


def import_page(
    request: Request,
    principal: Principal,
    import_id: str,
    *,
    notice: str | None = None,
    problem: FleetError | None = None,
) -> HTMLResponse:
    """One import's page; with `problem`, that error shown on it with its status."""
    found = records.import_json(imports_rest.ledger(request).row(import_id))
    return render(
        request,
        "import.html",
        principal,
        status=problem.http_status() if problem is not None else 200,
        imp=found,
        retryable=retryable(found),
        notice=notice,
        problem=problem,
        import_href=import_href,
        run_href=run_href,
    )


def retryable(found: dict[str, Any]) -> bool:
    """Whether `Importer.retry` takes this import: a failed MCAP import whose original is kept."""
    return bool(found["kind"] == "mcap" and found["state"] == rows.FAILED and found["quarantined"])


@router.get("/imports/{import_id}")
def one_import(request: Request, import_id: str, principal: Viewer) -> HTMLResponse:
    return import_page(request, principal, import_id, notice=NOTICES.get(request.query_params.get("done") or ""))


@router.post("/imports/{import_id}/retry")
async def retry(request: Request, import_id: str, principal: Viewer, _: Form) -> Response:
    """Convert the failed import again from its quarantined original, as `POST /v1/imports/ID/retry`
    does; back to its page saying how it went (its state and reason are the row's). A refusal (no
    write scope, an import that cannot be retried) is shown on the import's page with its status."""
    try:
        principal.require(Scope.WRITE)
        if request.app.state.ingest is None:
            raise UnavailableError("this node files no uploads (it runs no ingest): retry on a node that does")
        # No bearer header to pass on: a retry whose run another node owns is relayed with this
        # node's peer credential only (`fleet imports retry` passes the caller's token).
        filed = await imports_rest.importer(request).retry(import_id, None)
    except FleetError as exc:
        return await _page_off_loop(request, principal, import_id, exc)
    done = "retried" if filed.status < 400 else "retry-failed"
    return RedirectResponse(f"{import_href(import_id)}?done={done}", status_code=303)


async def _page_off_loop(request: Request, principal: Principal, import_id: str, exc: FleetError) -> HTMLResponse:
    """The import's page with the refusal on it, its catalog reads on a worker thread."""
    return await asyncio.to_thread(import_page, request, principal, import_id, problem=exc)


@router.get("/imports/{import_id}/original")
async def original(request: Request, import_id: str, principal: Viewer) -> Response:
    """An admin's download of the quarantined original, the same as `GET /v1/imports/ID/original`
    (the browser sends its session cookie, not a bearer token)."""
    principal.require(Scope.ADMIN)
    return await imports_rest.original_download(imports_rest.ledger(request), import_id)
