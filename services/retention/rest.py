"""REST: retention policies and plan, running it now, pins, restores, deletes, catalog rebuild.

Long work (`POST /v1/retention/run`, `POST /v1/catalog/rebuild`) answers NDJSON: one line per
run as it is done, so clients can show progress; the last line sums up.
"""

from __future__ import annotations

import functools
import json
import queue
import threading
from collections.abc import Callable, Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import StreamingResponse

from core.errors import BadParameterError
from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.retention import rebuild as rebuild_mod
from services.retention import schedule, service
from services.retention import scrub as scrub_mod
from services.retention.service import ACTIONS, Retention

router = APIRouter()
Reader = Annotated[Principal, Depends(require(Scope.READ))]
Writer = Annotated[Principal, Depends(require(Scope.WRITE))]
Admin = Annotated[Principal, Depends(require(Scope.ADMIN))]
NDJSON = "application/x-ndjson"


def _ctx(request: Request) -> Retention:
    ctx: Retention = request.app.state.retention
    return ctx


def _kinds(action: list[str] | None) -> list[str]:
    kinds = action or list(ACTIONS)
    for kind in kinds:
        if kind not in ACTIONS:
            raise BadParameterError("action", f"{kind!r} is not one of {', '.join(ACTIONS)}")
    return kinds


@router.get("/v1/retention", summary="Retention policies, settings and recent job runs")
def retention(request: Request, _: Reader) -> dict[str, Any]:
    return service.overview(_ctx(request), request.app.state.settings)


@router.get("/v1/retention/plan", summary="What would move or be deleted now, and why")
def retention_plan(
    request: Request,
    _: Reader,
    action: Annotated[list[str] | None, Query(description=" | ".join(ACTIONS) + " (repeatable; default all)")] = None,
) -> dict[str, Any]:
    return service.plan_answer(_ctx(request), _kinds(action))


@router.post("/v1/retention/run", summary="Do what is due now; NDJSON progress, one line per run")
def retention_run(
    request: Request,
    _: Admin,
    action: Annotated[list[str] | None, Query(description=" | ".join(ACTIONS) + " (repeatable; default all)")] = None,
) -> StreamingResponse:
    ctx, kinds = _ctx(request), _kinds(action)
    return StreamingResponse(_ndjson(functools.partial(schedule.run_now, ctx, kinds)), media_type=NDJSON)


def _ndjson(work: Callable[[Callable[[dict[str, Any]], None]], None]) -> Iterator[bytes]:
    """Run `work` on a thread, streaming what it emits as NDJSON lines while it runs."""
    lines: queue.Queue[dict[str, Any] | None] = queue.Queue()

    def target() -> None:
        try:
            work(lines.put)
        except Exception as exc:  # reported on the stream: the status line has been sent already
            lines.put({"event": "error", "detail": f"{type(exc).__name__}: {exc}"})
        finally:
            lines.put(None)

    threading.Thread(target=target, name="fleet-ndjson", daemon=True).start()
    while (line := lines.get()) is not None:
        yield (json.dumps(line) + "\n").encode()


@router.post("/v1/runs/{run_id}/pin", summary="Pin a run: exempt from expiry")
def pin(request: Request, run_id: str, principal: Writer) -> dict[str, Any]:
    return service.set_pinned(_ctx(request), run_id, True, actor(request, principal))


@router.delete("/v1/runs/{run_id}/pin", summary="Unpin a run: its policy applies again")
def unpin(request: Request, run_id: str, principal: Writer) -> dict[str, Any]:
    return service.set_pinned(_ctx(request), run_id, False, actor(request, principal))


@router.post("/v1/runs/{run_id}/promote", summary="Seal a closed hot run into the warm tier now")
def promote(request: Request, run_id: str, principal: Writer) -> dict[str, Any]:
    return service.promote_now(_ctx(request), run_id, actor(request, principal))


@router.post(
    "/v1/runs/{run_id}/restore",
    status_code=202,
    summary="Make a cold run readable again for restore_days (takes time; see restore_state)",
)
def restore(request: Request, run_id: str, principal: Writer) -> dict[str, Any]:
    return service.request_restore(_ctx(request), run_id, actor(request, principal))


@router.delete("/v1/runs/{run_id}", summary="Delete a sealed run now (objects first; a tombstone stays)")
def delete(
    request: Request,
    run_id: str,
    principal: Admin,
    force: Annotated[
        bool, Query(description="even a run a dataset snapshot uses (409 without): its episodes then answer missing")
    ] = False,
) -> dict[str, Any]:
    return service.delete_now(_ctx(request), run_id, actor(request, principal), force)


@router.post(
    "/v1/catalog/scrub-secrets",
    summary="Seal again without them the warm runs whose property chunks hold secret-like fields; NDJSON progress",
)
def scrub_secrets(
    request: Request,
    principal: Admin,
    dry_run: Annotated[bool, Query(description="only say which runs hold them")] = False,
) -> StreamingResponse:
    ctx = _ctx(request)
    work = functools.partial(scrub_mod.scrub_streamed, ctx, ctx.node.secret_fields, dry_run, actor(request, principal))
    return StreamingResponse(_ndjson(work), media_type=NDJSON)


@router.post("/v1/catalog/rebuild", summary="Add every sealed run found in the stores that the catalog lacks")
def rebuild(request: Request, _: Admin) -> StreamingResponse:
    ctx = _ctx(request)
    work = functools.partial(rebuild_mod.rebuild_streamed, ctx.catalog, ctx.tiers, ctx.clock)
    return StreamingResponse(_ndjson(work), media_type=NDJSON)
