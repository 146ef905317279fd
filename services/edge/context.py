"""What the edge routes work with (`Edge`), and the robot a robot's token acts for."""

from __future__ import annotations

from dataclasses import dataclass, field

from core.errors import PermissionDeniedError
from services.auth.scopes import Principal, Scope
from services.edge.cache import SealedChunkIds
from services.ingest.service import IngestService
from services.node import Node, OnNode


@dataclass
class Edge(OnNode):
    """The node, and this node's hot runs (None on a node without ingest), for the edge routes."""

    node: Node
    ingest: IngestService | None = None
    sealed_ids: SealedChunkIds = field(default_factory=SealedChunkIds)


def acting_robot(principal: Principal, free: Scope) -> str | None:
    """The one robot `principal` may act for (its ingest token's robot) when it lacks the `free`
    scope, which acts for every robot (None)."""
    if principal.allows(free):
        return None
    if principal.robot is None:  # the depot issues no ingest token without a robot
        raise PermissionDeniedError(
            f"the token of {principal.subject!r} is bound to no robot: this needs a robot's ingest token "
            f"or the {free.value!r} scope"
        )
    return principal.robot


def check_robot(bound: str | None, what: str, robot: str) -> None:
    """A robot's token (`bound`) acts on its own robot's runs and pulls only: 403 naming both robots."""
    if bound is not None and robot != bound:
        raise PermissionDeniedError(
            f"{what} belongs to robot {robot!r}, and this token acts for robot {bound!r} only: use that "
            "robot's token, or a token with a wider scope"
        )
