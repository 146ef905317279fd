"""Robot copies: what a robot's agent reports holding of a run (`PUT /v1/runs/RUN/robot-copy`),
and that it deleted it (`DELETE`). The latest report is kept, one per run; a run's page shows it,
so an engineer sees what exists only on the robot, and until when."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Any

from catalog import edge as edge_queries
from catalog import queries
from catalog.db import session_scope
from catalog.edge import RobotCopyReport
from core.errors import BadParameterError, NotFoundError
from core.ids import PATH_BYTES
from services.auth.scopes import Principal, Scope
from services.edge.context import Edge, acting_robot, check_robot

MAX_ENTITIES = 10_000


@dataclass(frozen=True)
class CopyFigures:
    """What the agent says it holds of the run: all of it, and what of it the depot lacks."""

    chunks: int
    bytes: int
    local_only_chunks: int = 0
    local_only_bytes: int = 0
    local_only_entities: list[str] = field(default_factory=list)
    keeps_until: dt.datetime | None = None  # when the robot deletes its copy

    def check(self) -> None:
        for name in ("chunks", "bytes", "local_only_chunks", "local_only_bytes"):
            if getattr(self, name) < 0:
                raise BadParameterError(name, f"{getattr(self, name)} is negative: count what the robot holds")
        for part in ("chunks", "bytes"):
            if getattr(self, f"local_only_{part}") > getattr(self, part):
                raise BadParameterError(
                    f"local_only_{part}",
                    f"{getattr(self, f'local_only_{part}')} is more than the copy's {getattr(self, part)} {part}: "
                    "what only the robot holds is part of its copy",
                )
        if len(self.local_only_entities) > MAX_ENTITIES:
            raise BadParameterError(
                "local_only_entities", f"{len(self.local_only_entities)} paths: at most {MAX_ENTITIES}"
            )
        for path in self.local_only_entities:
            if not path.startswith("/") or "\x00" in path or len(path.encode("utf-8", "surrogatepass")) > PATH_BYTES:
                raise BadParameterError(
                    "local_only_entities",
                    f"{path[:80]!r} is not an entity path: /a/b, at most {PATH_BYTES} bytes, no NUL",
                )


def not_catalogued(run_id: str) -> NotFoundError:
    return NotFoundError(
        f"no run {run_id!r} in the catalog yet: a run the depot receives is catalogued within seconds; "
        "retry later (and check the run id)"
    )


def report_copy(edge: Edge, principal: Principal, run_id: str, figures: CopyFigures) -> dict[str, Any]:
    """Store the robot's latest report of its copy of `run_id` (its own robot's ingest token, or
    admin); `{"robot_copy": ...}`."""
    figures.check()
    bound = acting_robot(principal, Scope.ADMIN)
    keeps_until = figures.keeps_until
    if keeps_until is not None and keeps_until.tzinfo is None:
        keeps_until = keeps_until.replace(tzinfo=dt.UTC)
    with session_scope(edge.catalog, write=True) as session:
        run = queries.get_run(session, run_id)
        if run is None:
            raise not_catalogued(run_id)
        check_robot(bound, f"run {run_id!r}", run.robot_id)
        row = edge_queries.save_robot_copy(
            session,
            RobotCopyReport(
                run_id=run_id,
                robot_id=run.robot_id,
                reported_at=edge.clock(),
                chunks=figures.chunks,
                bytes=figures.bytes,
                local_only_chunks=figures.local_only_chunks,
                local_only_bytes=figures.local_only_bytes,
                local_only_entities=list(figures.local_only_entities),
                keeps_until=keeps_until,
            ),
        )
        return {"robot_copy": edge_queries.robot_copy_dict(row)}


def forget_copy(edge: Edge, principal: Principal, run_id: str) -> dict[str, Any]:
    """The robot deleted its copy of `run_id`: its report is removed. `{"run": RUN, "removed":
    whether there was one, "robot_copy": null}`."""
    bound = acting_robot(principal, Scope.ADMIN)
    with session_scope(edge.catalog, write=True) as session:
        run = queries.get_run(session, run_id)
        if run is None:
            raise not_catalogued(run_id)
        check_robot(bound, f"run {run_id!r}", run.robot_id)
        removed = edge_queries.remove_robot_copy(session, run_id)
        return {"run": run_id, "removed": removed, "robot_copy": None}
