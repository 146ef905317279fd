"""REST: dataset snapshots (`/v1/datasets`): a selection resolved into a new immutable version,
snapshots and their versions, one version with a page of its episodes. Handlers parse the request
and call one service function; errors are mapped once by the app (`FleetError` -> status)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request
from pydantic import BaseModel, ConfigDict, Field, Strict, StrictInt

from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.datasets import service
from services.datasets.resolve import Sources
from services.datasets.selection import EventWindow, Selection, split_pairs
from services.runs.service import parse_time

router = APIRouter()
Reader = Annotated[Principal, Depends(require(Scope.READ))]
Writer = Annotated[Principal, Depends(require(Scope.WRITE))]
MAX_VERSION = 2**63 - 1
# A number of seconds, frames per second or a fraction: an integer too big for a float is refused here
Seconds = Annotated[float, Strict()]


def sources(request: Request) -> Sources:
    """Where this node reads runs from: its catalog, its hot runs, its warm store."""
    state = request.app.state
    return Sources(state.catalog, state.node.tiers.warm, state.ingest, state.node.clock)


class EventWindowBody(BaseModel):
    model_config = ConfigDict(extra="forbid")

    event: list[str] = Field(description="event kinds: an episode per event of any of them")
    before_s: Seconds = Field(0, description="seconds before the event's start (steps on a sequence timeline)")
    after_s: Seconds = Field(0, description="seconds after the event's end")


class DatasetBody(BaseModel):
    """A snapshot's name and selection: the run filters of `GET /v1/runs`, windows, entities, and
    what an export reads (timeline, fps) and how the runs are split."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(description="1 to 64 characters from A-Z a-z 0-9 . _ -, starting with a letter or digit")
    robot: list[str] = Field(default_factory=list)
    application: list[str] = Field(default_factory=list)
    since: str | None = Field(None, description="runs started at or after (ISO-8601)")
    until: str | None = Field(None, description="runs started before (ISO-8601)")
    status: str | None = None
    tier: str | None = None
    entity: list[str] = Field(default_factory=list, description="runs that have an entity: /a/b or /a/**")
    properties: dict[str, str] = Field(default_factory=dict, description='{"fleet.robot_id": "robot-7"}')
    metric: list[str] = Field(default_factory=list, description="NAME OP VALUE, e.g. distance_m>100")
    tag: list[str] = Field(default_factory=list)
    event: list[str] = Field(default_factory=list, description="runs with an event of each of these kinds")
    event_window: EventWindowBody | None = Field(None, description="an episode per event; none: one per run")
    include: list[str] = Field(default_factory=lambda: ["/**"], description="entities the episodes read")
    exclude: list[str] = Field(default_factory=list)
    timeline: str = Field("log_time", description="the timeline an export samples on")
    fps: Seconds | None = Field(None, description="the rate an export samples at")
    split: dict[str, Seconds] | None = Field(None, description='{"train": 0.9, "val": 0.1}: by run, seeded')
    seed: StrictInt = 0

    def selection(self) -> Selection:
        window = self.event_window
        return Selection(
            robot=tuple(self.robot),
            application=tuple(self.application),
            since=parse_time("since", self.since),
            until=parse_time("until", self.until),
            status=self.status,
            tier=self.tier,
            entity=tuple(self.entity),
            properties=tuple(self.properties.items()),
            metric=tuple(self.metric),
            tag=tuple(self.tag),
            event=tuple(self.event),
            event_window=EventWindow(tuple(window.event), float(window.before_s), float(window.after_s))
            if window is not None
            else None,
            include=tuple(self.include),
            exclude=tuple(self.exclude),
            timeline=self.timeline,
            fps=float(self.fps) if self.fps is not None else None,
            split=split_pairs(self.split),
            seed=self.seed,
        )


@router.post(
    "/v1/datasets", status_code=201, summary="Resolve a selection into a new immutable version of a dataset snapshot"
)
def create(request: Request, body: DatasetBody, principal: Writer) -> dict[str, Any]:
    """The version `NAME@N` written: its episodes (a run, or a window around one of its events, and
    the chunks each reads), counts by split, and the runs matched but skipped (with why)."""
    return service.create(sources(request), body.name, body.selection(), actor(request, principal))


@router.get("/v1/datasets", summary="Dataset snapshots, each with its latest version")
def datasets(request: Request, _: Reader) -> dict[str, Any]:
    return service.datasets_answer(sources(request))


@router.get("/v1/datasets/{name}", summary="A dataset snapshot's versions, newest first")
def dataset(request: Request, name: str, _: Reader) -> dict[str, Any]:
    return service.dataset_answer(sources(request), name)


@router.get("/v1/datasets/{name}/{version}", summary="One version: its selection and a page of its episodes")
def dataset_version(
    request: Request,
    name: str,
    version: Annotated[int, Path(ge=1, le=MAX_VERSION)],
    _: Reader,
    limit: Annotated[int, Query(description=f"episodes per page, 1 to {service.MAX_LIMIT}")] = 100,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
    chunk_ids: Annotated[bool, Query(description="list each episode's chunk ids (hex)")] = False,
) -> dict[str, Any]:
    return service.version_answer(sources(request), name, version, limit, cursor, chunk_ids)
