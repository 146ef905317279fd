"""REST: dataset exports (`/v1/exports`): a snapshot version queued for export by the depot into a
place it may write, jobs listed with their progress, one job, a cancel; and one episode's chunks as
an RRD stream (`/v1/datasets/NAME/N/episodes/K/recording.rrd`), which the command line exports
from. Handlers parse and call one service function; errors are mapped once by the app."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, Strict, StrictBool, StrictInt

from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.datasets import exports
from services.datasets.episodes import episode_recording, version_row
from services.datasets.export import ExportSpec
from services.datasets.exports import ExportRequest, Places
from services.datasets.quality import Limits
from services.datasets.rest import sources

router = APIRouter()
Reader = Annotated[Principal, Depends(require(Scope.READ))]
Writer = Annotated[Principal, Depends(require(Scope.WRITE))]
MAX_NUMBER = 2**63 - 1


class ExportBody(BaseModel):
    """What to export and where: the version, the format, the target, what goes where."""

    model_config = ConfigDict(extra="forbid")

    dataset: str = Field(description="the version: NAME@N")
    format: str = Field("lerobot", description="lerobot (LeRobot v3.0)")
    to: str = Field(description="file:///PATH or s3://BUCKET/PREFIX, under a place FLEET_EXPORT_URLS allows")
    observation: list[str] = Field(default_factory=list, description="entities of observation.state: /a/b or /a/**")
    action: list[str] = Field(default_factory=list, description="entities of action")
    cameras: dict[str, str] = Field(
        default_factory=dict, description='{"/camera/front": "observation.images.front"}: an Image entity per video'
    )
    task: str = Field("", max_length=1000, description="the episodes' task text")
    task_property: str | None = Field(None, description="a recording property NAME.FIELD as each run's task")
    fps: Annotated[int, Strict()] | None = Field(None, description="frames per second (default: the snapshot's)")
    video_codec: str = Field("h264", description="h264 or av1")
    strict: StrictBool = Field(False, description="refuse the export if any episode has a quality flag")
    frozen_s: Annotated[float, Strict()] = Field(
        2.0, gt=0, le=3600, description="a camera unchanged this long is frozen"
    )
    min_frames: StrictInt = Field(1, ge=0, le=10**9, description="an episode of fewer frames is short")


@router.post("/v1/exports", status_code=202, summary="Queue a dataset version's export into a place the depot writes")
def create(request: Request, body: ExportBody, principal: Writer) -> dict[str, Any]:
    """The job: `GET /v1/exports/ID` follows its progress. The depot writes only under
    FLEET_EXPORT_URLS; `fleet datasets export NAME@N --to DIR` exports to a folder of your own."""
    name, version = exports.parse_version(body.dataset)
    src = sources(request)
    fps = body.fps if body.fps is not None else exports.default_fps(json.loads(version_row(src, name, version)[1]))
    spec = ExportSpec(
        tuple(body.observation),
        tuple(body.action),
        tuple(body.cameras.items()),
        body.task,
        fps,
        body.video_codec,
        body.task_property,
    )
    request_ = ExportRequest(
        name, version, body.format, body.to, spec, Limits(float(body.frozen_s), body.min_frames), body.strict
    )
    return exports.create(src, Places.of(request.app.state.node.settings), request_, actor(request, principal))


@router.get("/v1/exports", summary="Dataset exports, newest first, with their progress")
def listed(
    request: Request,
    _: Reader,
    dataset: Annotated[str | None, Query(description="NAME or NAME@N")] = None,
    limit: Annotated[int, Query(description=f"1 to {exports.MAX_LIMIT}")] = 50,
) -> dict[str, Any]:
    return exports.jobs_answer(sources(request), dataset, limit)


@router.get("/v1/exports/{job_id}", summary="One export: its state, progress and quality report")
def one(request: Request, job_id: str, _: Reader) -> dict[str, Any]:
    return exports.job_answer(sources(request), job_id)


@router.delete("/v1/exports/{job_id}", summary="Cancel a queued or running export")
def cancel(request: Request, job_id: str, _: Writer) -> dict[str, Any]:
    return exports.cancel(sources(request), job_id)


@router.get(
    "/v1/datasets/{name}/{version}/episodes/{episode}/recording.rrd",
    summary="The chunks one episode of a version reads, as an RRD stream",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
async def episode(
    request: Request,
    name: str,
    version: Annotated[int, Path(ge=1, le=MAX_NUMBER)],
    episode: Annotated[int, Path(ge=0, le=MAX_NUMBER)],
    _: Reader,
) -> StreamingResponse:
    """Exactly the snapshot's chunks of the episode (its run's recording info first), whatever the
    run holds now: `rerun URL` opens it, `fleet datasets export --to DIR` reads it."""
    body = await asyncio.to_thread(episode_recording, sources(request), name, version, episode)
    filename = f"{name}@{version}-episode-{episode}.rrd"
    return StreamingResponse(
        body,
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )
