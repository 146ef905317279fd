"""REST: what a robot's agent asks of the depot (`held`, its pulls, its copies) and what engineers
ask of robots (pulls of runs, and of events' windows). Handlers parse, call one function of the
edge package, and leave errors to the app's one mapping. Plain `def` handlers: FastAPI runs them
on worker threads, so reading a sealed run's chunk index never blocks the event loop (`held`, which
may ask the node that owns the run, is async and does its own work on a worker thread)."""

from __future__ import annotations

import asyncio
import datetime as dt
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from catalog.edge import PullAsk
from core.states import PullState
from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.cluster import peer
from services.edge import copies, held, pulls, triggers
from services.edge.context import Edge
from services.ingest.routing import asking_for, owner_elsewhere

router = APIRouter()
Count = Annotated[int, Field(ge=0, le=2**63 - 1)]  # what a catalog BIGINT holds


def _edge(request: Request) -> Edge:
    edge: Edge = request.app.state.edge
    return edge


class HeldBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    chunk_ids: list[Any] = Field(description="1 to 100000 chunk ids, each 32 lowercase hex digits")


@router.post("/v1/runs/{run_id}/held", summary="Which of these chunks of a run the depot holds, and how safely")
async def held_chunks(
    request: Request,
    run_id: str,
    body: HeldBody,
    principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.READ))],
) -> dict[str, Any]:
    """Each chunk id is in `missing` (held nowhere), in `unsealed` (only in the hot tier of the
    node that owns the run) or counted in `sealed` (in the warm tier). A cold or deleted run takes
    no data: `accepts_data` false, nothing missing. A robot's ingest token asks about its own
    robot's runs, or runs the depot does not know."""
    edge = _edge(request)
    owner = await owner_elsewhere(edge.ingest, run_id) if edge.ingest is not None else None
    if owner is not None and edge.ingest is not None:  # hot on another node of the depot: asked there
        assert edge.node.channels is not None  # a node with owners has channels to them
        asked = {"run_id": run_id, "chunk_ids": body.chunk_ids}
        metadata = asking_for(edge.ingest, edge.node.auth, principal)
        return await peer.held(edge.node.channels, owner, asked, metadata)
    return await asyncio.to_thread(held.held_answer, edge, principal, run_id, body.chunk_ids)


class PullBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    include: list[str] = Field(default_factory=list, description="entity patterns to send: /a/b or /a/**")
    exclude: list[str] = Field(default_factory=list, description="entity patterns to leave out; wins over include")
    timeline: str | None = Field(None, description="send chunks overlapping [start, end] on this timeline")
    start: str | None = Field(None, description="as a download takes it: sequence, duration or timestamp")
    end: str | None = Field(None, description="as start; inclusive")


@router.post(
    "/v1/runs/{run_id}/pull",
    status_code=202,
    summary="Ask the run's robot to send (part of) it: queued for its agent",
    responses={200: {"description": "the same pull was pending or sending already: that one"}},
)
def request_pull(
    request: Request,
    response: Response,
    run_id: str,
    body: PullBody,
    principal: Annotated[Principal, Depends(require(Scope.WRITE))],
) -> dict[str, Any]:
    ask = PullAsk(run_id, body.include, body.exclude, body.timeline, body.start, body.end)
    answer, created = pulls.request_pull(_edge(request), ask, actor(request, principal))
    if not created:
        response.status_code = 200
    return answer


@router.post(
    "/v1/events/{event_id}/pull",
    status_code=202,
    summary="Ask the robot for an event's window (the one its trigger asked for): queued for its agent",
    responses={200: {"description": "a pull of the event was pending or sending already: that one"}},
)
def pull_event(
    request: Request,
    response: Response,
    event_id: str,
    principal: Annotated[Principal, Depends(require(Scope.WRITE))],
) -> dict[str, Any]:
    """A person's pull of the window the event's newest trigger pull asked for (one held on the
    robot over its budget, or that failed). 409 for an event no trigger pulled: no window of it is
    known (pull a window of its run instead)."""
    answer, created = triggers.pull_event(_edge(request), event_id, actor(request, principal))
    if not created:
        response.status_code = 200
    return answer


@router.get("/v1/runs/{run_id}/pulls", summary="A run's pulls, newest first")
def run_pulls(request: Request, run_id: str, _: Annotated[Principal, Depends(require(Scope.READ))]) -> dict[str, Any]:
    return pulls.run_pulls_answer(_edge(request), run_id)


@router.get("/v1/pulls", summary="Pulls by state and robot, oldest first: what a robot's agent polls")
def list_pulls(
    request: Request,
    principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.READ))],
    state: Annotated[str | None, Query(description=" | ".join(PullState))] = None,
    robot: Annotated[str | None, Query(description="robot id; a robot's ingest token: its own (the default)")] = None,
    limit: Annotated[int, Query(description=f"1 to {pulls.MAX_LIMIT}")] = 100,
) -> dict[str, Any]:
    return pulls.pulls_answer(_edge(request), principal, pulls.PullQuery(state, robot, limit))


class ProgressBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    state: str = Field(description="sending | done | failed | held")
    chunks_sent: Count
    bytes_sent: Count
    error: str | None = Field(None, description="why it failed (kept up to 2000 characters)")


@router.post("/v1/pulls/{pull_id}/progress", summary="A robot's agent reports how far it got with a pull")
def pull_progress(
    request: Request,
    pull_id: str,
    body: ProgressBody,
    principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.WRITE))],
) -> dict[str, Any]:
    """pending -> sending -> done | failed, pending -> failed, pending or sending -> held (kept on
    the robot: over its trigger's budget, `error` saying so); the same state again updates the
    counters. A done, failed, cancelled or held pull answers 409 naming its state."""
    progress = pulls.Progress(body.state, body.chunks_sent, body.bytes_sent, body.error)
    return pulls.report_progress(_edge(request), principal, pull_id, progress)


@router.post("/v1/pulls/{pull_id}/cancel", summary="Cancel a pending or sending pull, or dismiss a held one")
def cancel_pull(
    request: Request, pull_id: str, _: Annotated[Principal, Depends(require(Scope.WRITE))]
) -> dict[str, Any]:
    return pulls.cancel_pull(_edge(request), pull_id)


class RobotCopyBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    chunks: Count
    bytes: Count
    local_only_chunks: Count = Field(0, description="chunks the depot does not hold")
    local_only_bytes: Count = 0
    local_only_entities: list[str] = Field(default_factory=list, description="entity paths of those chunks")
    keeps_until: dt.datetime | None = Field(None, description="when the robot deletes its copy (ISO-8601)")


@router.put("/v1/runs/{run_id}/robot-copy", summary="A robot's agent reports what it holds of a run")
def report_robot_copy(
    request: Request,
    run_id: str,
    body: RobotCopyBody,
    principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.ADMIN))],
) -> dict[str, Any]:
    """The latest report replaces the one before. 404 (retry later) for a run the catalog does
    not have yet."""
    figures = copies.CopyFigures(**body.model_dump())
    return copies.report_copy(_edge(request), principal, run_id, figures)


@router.delete("/v1/runs/{run_id}/robot-copy", summary="A robot's agent deleted its copy of a run")
def forget_robot_copy(
    request: Request, run_id: str, principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.ADMIN))]
) -> dict[str, Any]:
    return copies.forget_copy(_edge(request), principal, run_id)
