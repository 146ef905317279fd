"""The peer port's `fleet.peer.v1.Peer` service: what another node of the depot asks of this one
about a hot run it owns (see `services.cluster.peer`, the asking side). The asking node checked its
caller and sends a short-lived token of its own carrying that caller's scopes and robot; this node
checks that token and answers as it would answer the caller."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from collections.abc import AsyncIterator, Iterator
from typing import Any, NoReturn, TypeVar

import grpc
from pydantic import TypeAdapter, ValidationError
from sqlalchemy.orm import Session, sessionmaker

from core.errors import FleetError, InvalidArgumentError
from services.auth.metadata import call_principal
from services.auth.scopes import Principal, Scope
from services.auth.tokens import Auth
from services.cluster.peer import SERVICE
from services.cluster.relay import ERROR_CODE
from services.edge import held
from services.edge.context import Edge
from services.ingest.service import IngestService
from services.runs.recording import RecordingQuery, recording_download
from services.storage.objectstore import ObjectStore

_QUERY_FIELDS = {f.name for f in dataclasses.fields(RecordingQuery)}


class PeerService:
    def __init__(
        self, auth: Auth, ingest: IngestService, catalog: sessionmaker[Session], warm: ObjectStore | None, edge: Edge
    ) -> None:
        self.auth = auth
        self.ingest = ingest
        self.catalog = catalog
        self.warm = warm
        self.edge = edge

    async def _principal(self, context: grpc.aio.ServicerContext, *scopes: Scope) -> Principal:
        return await call_principal(self.auth, context.invocation_metadata(), *scopes)

    async def read_hot(self, request: bytes, context: grpc.aio.ServicerContext) -> AsyncIterator[bytes]:
        """A recording download, as `GET /v1/runs/RUN/recording.rrd` would stream it here."""
        try:
            await self._principal(context, Scope.READ)
            asked = _json(request)
            run_id = _text(asked, "run_id")
            query = _typed(_QUERY, {k: v for k, v in asked.items() if k in _QUERY_FIELDS}, "query")
            found = await asyncio.to_thread(recording_download, self.ingest, self.catalog, self.warm, run_id, query)
            if isinstance(found.body, Iterator):
                pieces = iter(found.body)
                while (piece := await asyncio.to_thread(next, pieces, None)) is not None:
                    yield bytes(piece)
            else:
                async for piece in found.body:
                    yield bytes(piece)
        except FleetError as exc:
            await _refuse(context, exc)

    async def held(self, request: bytes, context: grpc.aio.ServicerContext) -> bytes:
        """`POST /v1/runs/RUN/held`, answered here."""
        try:
            principal = await self._principal(context, *Scope)
            asked = _json(request)
            chunk_ids = _typed(_CHUNK_IDS, asked.get("chunk_ids", []), "chunk_ids")
            answer = await asyncio.to_thread(held.held_answer, self.edge, principal, _text(asked, "run_id"), chunk_ids)
        except FleetError as exc:
            await _refuse(context, exc)
        return json.dumps(answer).encode()


_QUERY: TypeAdapter[RecordingQuery] = TypeAdapter(RecordingQuery)
_CHUNK_IDS: TypeAdapter[list[str]] = TypeAdapter(list[str])
T = TypeVar("T")


def _typed(adapter: TypeAdapter[T], value: object, name: str) -> T:
    """`value` (from JSON) as the type the adapter stands for, its JSON types as they are (no coercion)."""
    try:
        return adapter.validate_json(json.dumps(value), strict=True)
    except ValidationError as exc:
        where = ".".join([name, *(str(p) for p in exc.errors()[0]["loc"])])
        raise InvalidArgumentError(f"a peer request's {where} is of the wrong type: {exc.errors()[0]['msg']}") from None


def _text(asked: dict[str, Any], key: str) -> str:
    value = asked.get(key, "")
    if not isinstance(value, str):
        raise InvalidArgumentError(f"a peer request's {key} must be a string")
    return value


def _json(request: bytes) -> dict[str, Any]:
    try:
        value = json.loads(request)
    except ValueError:
        raise InvalidArgumentError("a peer request must be a JSON object") from None
    if not isinstance(value, dict):
        raise InvalidArgumentError("a peer request must be a JSON object")
    return value


async def _refuse(context: grpc.aio.ServicerContext, exc: FleetError) -> NoReturn:
    context.set_trailing_metadata(((ERROR_CODE, exc.code.name),))
    await context.abort(grpc.StatusCode[exc.grpc_status()], str(exc))
    raise AssertionError("not reached: abort raises")


def add_to_server(server: grpc.aio.Server, service: PeerService) -> None:
    handlers = {
        "ReadHot": grpc.unary_stream_rpc_method_handler(
            service.read_hot, request_deserializer=None, response_serializer=None
        ),
        "Held": grpc.unary_unary_rpc_method_handler(service.held, request_deserializer=None, response_serializer=None),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE, handlers),))
    server.add_registered_method_handlers(SERVICE, handlers)
