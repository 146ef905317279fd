"""REST: `POST /v1/rules/backfill`, the rules backfill now, with NDJSON progress (one line per run,
the last one the summary), as `POST /v1/retention/run` streams its own."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import StreamingResponse

from core.errors import UnavailableError
from services.auth.depends import require
from services.auth.scopes import Principal, Scope
from services.corpus.backfill import Emit, RulesBackfill
from services.retention.rest import NDJSON, _ndjson

router = APIRouter()
Writer = Annotated[Principal, Depends(require(Scope.WRITE))]


@router.post(
    "/v1/rules/backfill",
    summary="Evaluate every stored run the running rules have not; NDJSON progress, one line per run",
)
def rules_backfill(request: Request, _: Writer) -> StreamingResponse:
    backfill: RulesBackfill | None = getattr(request.app.state, "rules_backfill", None)
    if backfill is None:
        raise UnavailableError("this node does not evaluate rules")

    def work(emit: Emit) -> None:
        backfill.run(emit)

    return StreamingResponse(_ndjson(work), media_type=NDJSON)
