"""REST: the rules file (`/v1/rules`), events (`/v1/events`, `/v1/runs/{run}/events`), the
triggers robots' agents fired (`/v1/runs/{run}/triggered`) and run tags (`/v1/runs/{run}/tags`).
Handlers parse the request and call one service function; errors are mapped once by the app
(`FleetError` -> status)."""

from __future__ import annotations

import secrets
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict, Field, StrictInt, StrictStr

from catalog.edge import PullAsk
from core.errors import BadParameterError
from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.corpus import service
from services.corpus import triggered as triggered_reports
from services.corpus.links import Viewer
from services.runs.links import lifetime, request_base
from services.runs.service import parse_time

router = APIRouter()
Reader = Annotated[Principal, Depends(require(Scope.READ))]
RulesReader = Annotated[Principal, Depends(require(Scope.INGEST, Scope.READ))]  # a robot's agent reads the rules
Writer = Annotated[Principal, Depends(require(Scope.WRITE))]
RULES_TYPES = ("text/plain", "application/toml")
MAX_RULES_BODY = 2 * 1024 * 1024  # the rules language refuses more than half of this, naming the size
MAX_VERSION = 2**63 - 1  # the catalog's BigInteger: a larger number is no version (and no query error)


def viewer(request: Request, principal: Principal) -> Viewer:
    """How this request's event answers link to the viewer: signed with its grant, to the depot's
    public address, for the depot's link lifetime."""
    state = request.app.state
    return Viewer(state.auth, principal, request_base(request), lifetime(None, state.settings.link_ttl_s))


# --- rules ------------------------------------------------------------------------------------------


@router.put(
    "/v1/rules",
    summary="Apply a rules file (TOML, the body as is): checked whole, recorded as a new version",
    openapi_extra={"requestBody": {"content": {t: {"schema": {"type": "string"}} for t in RULES_TYPES}}},
)
async def apply_rules(request: Request, principal: Writer) -> dict[str, Any]:
    """The body is the TOML file (Content-Type text/plain or application/toml). A file with any
    problem is refused whole (422 listing every problem with its line and field) and the running set
    stays; the same text as the running set makes no new version (`changed` false)."""
    text = await _rules_text(request)
    state = request.app.state
    return await run_in_threadpool(
        service.apply_rules,
        state.catalog,
        text,
        actor(request, principal),
        state.node.clock(),
        getattr(state, "rules_applied", None),
    )


async def _rules_text(request: Request) -> str:
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind not in RULES_TYPES:
        raise BadParameterError("content-type", f"{kind or 'none'}: send the TOML file as {' or '.join(RULES_TYPES)}")
    body = bytearray()
    async for piece in request.stream():
        body += piece
        if len(body) > MAX_RULES_BODY:
            raise BadParameterError("body", f"more than {MAX_RULES_BODY} bytes: a rules file is smaller")
    try:
        return body.decode()
    except UnicodeDecodeError:
        raise BadParameterError("body", "a rules file is UTF-8 text") from None


@router.get("/v1/rules", summary="The running rules (or an older version): text, rules, who applied it and when")
def rules(
    request: Request,
    _: RulesReader,
    version: Annotated[
        int | None, Query(description="an older version (see /v1/rules/history)", ge=1, le=MAX_VERSION)
    ] = None,
) -> dict[str, Any]:
    return service.rules_answer(request.app.state.catalog, version)


@router.get("/v1/rules/history", summary="Every version of the rules, newest first, with who and when")
def rules_history(request: Request, _: Reader) -> dict[str, Any]:
    return service.rules_history_answer(request.app.state.catalog)


# --- events -----------------------------------------------------------------------------------------


@router.get("/v1/events", summary="Events fleet-wide, filtered, newest first, a page at a time")
def events(
    request: Request,
    principal: Reader,
    kind: Annotated[list[str] | None, Query(description="event kind (repeatable)")] = None,
    robot: Annotated[list[str] | None, Query(description="robot id (repeatable)")] = None,
    run: Annotated[list[str] | None, Query(description="run id (repeatable)")] = None,
    severity: Annotated[list[str] | None, Query(description=" | ".join(service.SEVERITIES))] = None,
    origin: Annotated[list[str] | None, Query(description=" | ".join(service.ORIGINS))] = None,
    source: Annotated[str | None, Query(description="`rule NAME@VERSION`, a person's name, or `robot`")] = None,
    since: Annotated[str | None, Query(description="recorded by the depot at or after (ISO-8601)")] = None,
    until: Annotated[str | None, Query(description="recorded by the depot before (ISO-8601)")] = None,
    pending: Annotated[
        bool, Query(description="only events whose window is asked of the robot and not at the depot yet")
    ] = False,
    limit: Annotated[int, Query(description=f"1 to {service.MAX_LIMIT}")] = 100,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
) -> dict[str, Any]:
    flt = service.EventFilter(
        kind=kind or [],
        robot=robot or [],
        run=run or [],
        severity=severity or [],
        origin=origin or [],
        source=source,
        since=parse_time("since", since),
        until=parse_time("until", until),
        pending=pending,
        limit=limit,
        cursor=cursor,
    )
    return service.events_answer(request.app.state.catalog, viewer(request, principal), flt)


@router.get("/v1/events/{event_id}", summary="One event, with a link that opens its window in the viewer")
def event(request: Request, event_id: str, principal: Reader) -> dict[str, Any]:
    return service.one_event_answer(request.app.state.catalog, viewer(request, principal), event_id)


@router.get("/v1/runs/{run_id}/events", summary="A run's events, in timeline order")
def run_events(request: Request, run_id: str, principal: Reader) -> dict[str, Any]:
    return service.run_events_answer(request.app.state.catalog, viewer(request, principal), run_id)


class AnnotationBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    timeline: str = Field(description="one of the run's timelines, e.g. log_time")
    start: StrictStr | StrictInt = Field(
        description="ISO-8601 or ns (timestamp), an integer (sequence), 12.5s or ns (duration)"
    )
    end: StrictStr | StrictInt | None = Field(None, description="as start; none: an instant")
    label: str = ""
    note: str = ""
    severity: str = Field("info", description=" | ".join(service.SEVERITIES))
    kind: str = service.PERSON_KIND


@router.post("/v1/runs/{run_id}/events", summary="Annotate a run: a person's event on one of its timelines")
def annotate(request: Request, run_id: str, body: AnnotationBody, principal: Writer) -> dict[str, Any]:
    asked = service.Annotation(**body.model_dump())
    state = request.app.state
    new_id = "ev-" + secrets.token_hex(8)
    return service.annotate(
        state.catalog, viewer(request, principal), run_id, asked, actor(request, principal), state.node.clock(), new_id
    )


# --- triggers a robot's agent fired ------------------------------------------------------------------

Position = Annotated[StrictInt, Field(ge=-(2**63), le=2**63 - 1, description="on the event's timeline")]
Count = Annotated[StrictInt, Field(ge=0, le=2**63 - 1)]


class TriggeredEventBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: str = Field(description="the [[event]] rule's name")
    severity: str = Field(description=" | ".join(service.SEVERITIES))
    timeline: str
    timeline_type: str = Field(description="timestamp | sequence | duration")
    start: Position
    end: Position
    label: str = ""


class TriggeredWindowBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    timeline: str | None = Field(None, description="the window's timeline (the event's)")
    start: str | None = Field(None, description="as a pull takes it: ns on a timestamp timeline")
    end: str | None = None
    include: list[str] = Field(default_factory=list, description="the trigger's entities: /a/b or /a/**")
    exclude: list[str] = Field(default_factory=list)


class TriggeredBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    pull_id: str = Field(description="chosen by the agent: 'pull-' and 12 lowercase hex digits")
    rules_version: Annotated[StrictInt, Field(ge=1, le=MAX_VERSION, description="the rules that fired it")]
    event: TriggeredEventBody
    window: TriggeredWindowBody
    priority: str = Field("normal", description="high | normal")
    state: str = Field(description="pending | sending | held | done")
    chunks_sent: Count = 0
    bytes_sent: Count = 0
    error: str | None = Field(None, description="why it is held (over budget: ...)")


@router.post(
    "/v1/runs/{run_id}/triggered",
    status_code=201,
    summary="A robot's agent reports a trigger it fired: the event, and the pull bringing its window home",
    responses={200: {"description": "reported before (the same pull id), or the depot's pull of the event"}},
)
def triggered(
    request: Request,
    response: Response,
    run_id: str,
    body: TriggeredBody,
    principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.WRITE))],
) -> dict[str, Any]:
    """`{"event": ..., "pull": ...}`: the event as `GET /v1/events/ID` answers it, and the pull the
    agent reports progress on (`POST /v1/pulls/ID/progress`): the one it named, or the depot's own
    pull of the same event if the depot fired first. A robot's ingest token reports on its own
    robot's runs; 404 (retry later) for a run the catalog does not have yet."""
    window = body.window
    report = triggered_reports.Triggered(
        pull_id=body.pull_id,
        rules_version=body.rules_version,
        event=triggered_reports.ReportedEvent(**body.event.model_dump()),
        window=PullAsk(run_id, window.include, window.exclude, window.timeline, window.start, window.end),
        priority=body.priority,
        state=body.state,
        chunks_sent=body.chunks_sent,
        bytes_sent=body.bytes_sent,
        error=body.error,
    )
    state = request.app.state
    answer, created = triggered_reports.report_triggered(
        state.catalog, viewer(request, principal), principal, run_id, report, state.node.clock()
    )
    if not created:
        response.status_code = 200
    return answer


# --- tags -------------------------------------------------------------------------------------------


class TagsBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tags: list[str] = Field(description="1 to 128 characters each, no whitespace or comma")


@router.post("/v1/runs/{run_id}/tags", summary="Tag a run (who added each tag is kept)")
def tag(request: Request, run_id: str, body: TagsBody, principal: Writer) -> dict[str, Any]:
    state = request.app.state
    return service.add_tags(state.catalog, run_id, body.tags, actor(request, principal), state.node.clock())


@router.delete("/v1/runs/{run_id}/tags", summary='Untag a run: tags by `?tag=` or a body {"tags": [...]}')
def untag(
    request: Request,
    run_id: str,
    _: Writer,
    tag: Annotated[list[str] | None, Query(description="a tag to remove (repeatable)")] = None,
    body: Annotated[TagsBody | None, Body()] = None,
) -> dict[str, Any]:
    tags = [*(tag or []), *(body.tags if body is not None else [])]
    return service.remove_tags(request.app.state.catalog, run_id, tags)
