"""gRPC `rerun.cloud.v1alpha1.RerunCloudService`: parse the call (its token, its
`x-rerun-entry-id`, its client version), call a service function off the event loop, and map
errors to gRPC statuses. The answers are built in `entries`, `segments`, `manifest`, `chunks` and
`query`. Writes to an entry are refused (`entries.refuse_write`): a snapshot version's as
FAILED_PRECONDITION, the others as UNIMPLEMENTED."""

from __future__ import annotations

import asyncio
import logging
import sys
from collections.abc import AsyncIterator, Callable, Iterable, Iterator
from typing import Any, NoReturn, TypeVar

import grpc
from google.protobuf.message import DecodeError, Message

from core.errors import FleetError, InvalidArgumentError, as_fleet_error
from services.auth.metadata import call_principal
from services.auth.scopes import Principal, Scope
from services.auth.tokens import Auth
from services.redap import chunks, entries, manifest, query, segments
from services.redap.clients import check_client
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2, cloud_pb2_grpc
from services.redap.tuid import Tuid
from services.rrd import errors as rrd_errors
from services.rrd.pb import common_pb2
from services.rrd.protowire import last_field

log = logging.getLogger(__name__)

ENTRY_ID_HEADER = "x-rerun-entry-id"
R = TypeVar("R", bound=Message)
T = TypeVar("T")
Metadata = Iterable[tuple[str, Any]] | None


def entry_id(metadata: Metadata) -> Tuid:
    """The dataset or table a call is about: its `x-rerun-entry-id` header (INVALID_ARGUMENT without)."""
    for key, value in metadata or ():
        if key == ENTRY_ID_HEADER:
            return Tuid.parse(value.decode() if isinstance(value, bytes) else str(value))
    raise InvalidArgumentError(f"this call needs the {ENTRY_ID_HEADER} header naming a dataset or table")


def header_entry_id(metadata: Metadata) -> Tuid | None:
    """The `x-rerun-entry-id` header's entry, if the call has one (INVALID_ARGUMENT if malformed)."""
    for key, value in metadata or ():
        if key == ENTRY_ID_HEADER:
            return Tuid.parse(value.decode() if isinstance(value, bytes) else str(value))
    return None


def _table_call(answer: Callable[..., T], context: Any, body: common_pb2.EntryId | None) -> Callable[..., T]:
    """`answer(depot, principal, table id, request)` with the table named by the call's header or,
    for clients from before that header, by its request body (`entries.table_id`); resolved on the
    worker thread after the caller's token is checked."""
    metadata = context.invocation_metadata()

    def call(depot: Depot, principal: Principal, request: Any) -> T:
        return answer(depot, principal, entries.table_id(header_entry_id(metadata), body), request)

    return call


async def _abort(context: grpc.aio.ServicerContext, exc: FleetError) -> NoReturn:
    await context.abort(grpc.StatusCode[exc.grpc_status()], str(exc))
    raise AssertionError("not reached: abort raises")


async def _internal(context: grpc.aio.ServicerContext) -> NoReturn:
    """A failure no error of ours describes: a catalog that did not answer is UNAVAILABLE (as REST
    answers 503); any other is a fault of the depot, logged whole, answered INTERNAL rather than
    gRPC's UNKNOWN with the exception's text."""
    known = as_fleet_error(sys.exc_info()[1] or Exception())
    if known is not None:
        log.warning("catalog service call failed: %s", known)
        await _abort(context, known)
    log.exception("catalog service call failed")
    await context.abort(grpc.StatusCode.INTERNAL, "internal error of the depot (its log has the details)")
    raise AssertionError("not reached: abort raises")


class CatalogServer(cloud_pb2_grpc.RerunCloudServiceServicer):
    """One method per RPC. Streaming RPCs are async generators themselves (`async for ... yield`
    over `_stream`): grpc.aio takes a plain method that returns an async generator for a
    synchronous iterator, and every call then fails."""

    def __init__(self, depot: Depot, auth: Auth) -> None:
        self.depot = depot
        self.auth = auth

    async def _caller(self, context: grpc.aio.ServicerContext, *scopes: Scope) -> Principal:
        metadata = context.invocation_metadata()
        principal = await call_principal(self.auth, metadata, *scopes)
        check_client(metadata)
        return principal

    async def parsed(
        self, raw: bytes, parse: Callable[[bytes], Message], context: grpc.aio.ServicerContext, *, open_call: bool
    ) -> Message:
        """A call's request, parsed only once its token is known to be valid (`open_call`: a call
        anyone may make); INVALID_ARGUMENT if it is not the request protobuf."""
        try:
            if not open_call:
                await call_principal(self.auth, context.invocation_metadata(), *Scope)
            try:
                return parse(raw)
            except (DecodeError, ValueError, TypeError) as exc:
                raise InvalidArgumentError(
                    f"the request is not a valid {_request_name(parse)} protobuf ({exc}): send it as Rerun's clients do"
                ) from None
        except FleetError as exc:
            await _abort(context, exc)

    async def _unary(
        self,
        context: grpc.aio.ServicerContext,
        answer: Callable[..., R],
        *args: Any,
        scopes: tuple[Scope, ...],
        entry: bool = False,
    ) -> R:
        """`answer(depot, principal, [entry id,] *args)` on a worker thread; `entry`: the call names
        its dataset or table by header."""
        try:
            principal = await self._caller(context, *scopes)
            named = (entry_id(context.invocation_metadata()),) if entry else ()
            return await asyncio.to_thread(answer, self.depot, principal, *named, *args)
        except FleetError as exc:
            await _abort(context, exc)
        except grpc.aio.AbortError:
            raise
        except Exception:
            await _internal(context)

    async def _stream(
        self,
        context: grpc.aio.ServicerContext,
        answers: Callable[..., Iterator[R]],
        *args: Any,
        scopes: tuple[Scope, ...],
        entry: bool = False,
    ) -> AsyncIterator[R]:
        """As `_unary`, for a stream: each response made on a worker thread, one at a time, so a
        large answer is never whole in memory and the event loop never blocks."""
        try:
            principal = await self._caller(context, *scopes)
            named = (entry_id(context.invocation_metadata()),) if entry else ()
            made = await asyncio.to_thread(answers, self.depot, principal, *named, *args)
            while (response := await asyncio.to_thread(next, made, None)) is not None:
                yield response
        except FleetError as exc:
            await _abort(context, exc)
        except grpc.aio.AbortError:
            raise
        except Exception:
            await _internal(context)

    # --- the server and its catalog -------------------------------------------------------

    async def Version(self, request: cloud_pb2.VersionRequest, context: Any) -> cloud_pb2.VersionResponse:
        return entries.version()  # open, as Rerun's own servers answer it

    async def WhoAmI(self, request: cloud_pb2.WhoAmIRequest, context: Any) -> cloud_pb2.WhoAmIResponse:
        # Any valid token may ask what it may do; anonymous callers are UNAUTHENTICATED when auth is on,
        # which is what makes Rerun's clients offer a token.
        return await self._unary(context, entries.who_am_i, scopes=tuple(Scope))

    async def FindEntries(self, request: cloud_pb2.FindEntriesRequest, context: Any) -> cloud_pb2.FindEntriesResponse:
        return await self._unary(context, entries.find_entries, request, scopes=(Scope.READ,))

    async def ReadDatasetEntry(
        self, request: cloud_pb2.ReadDatasetEntryRequest, context: Any
    ) -> cloud_pb2.ReadDatasetEntryResponse:
        return await self._unary(context, entries.read_dataset_entry, scopes=(Scope.READ,), entry=True)

    async def ReadTableEntry(
        self, request: cloud_pb2.ReadTableEntryRequest, context: Any
    ) -> cloud_pb2.ReadTableEntryResponse:
        named = _table_call(entries.read_table_entry, context, request.id if request.HasField("id") else None)
        return await self._unary(context, named, request, scopes=(Scope.READ,))

    async def GetTableSchema(
        self, request: cloud_pb2.GetTableSchemaRequest, context: Any
    ) -> cloud_pb2.GetTableSchemaResponse:
        named = _table_call(entries.table_schema, context, request.table_id if request.HasField("table_id") else None)
        return await self._unary(context, named, request, scopes=(Scope.READ,))

    async def ScanTable(
        self, request: cloud_pb2.ScanTableRequest, context: Any
    ) -> AsyncIterator[cloud_pb2.ScanTableResponse]:
        named = _table_call(entries.scan_table, context, request.table_id if request.HasField("table_id") else None)
        async for response in self._stream(context, named, request, scopes=(Scope.READ,)):
            yield response

    # --- a dataset's segments (runs) -------------------------------------------------------

    async def GetSegmentTableSchema(
        self, request: cloud_pb2.GetSegmentTableSchemaRequest, context: Any
    ) -> cloud_pb2.GetSegmentTableSchemaResponse:
        return await self._unary(context, segments.table_schema, scopes=(Scope.READ,), entry=True)

    async def ScanSegmentTable(
        self, request: cloud_pb2.ScanSegmentTableRequest, context: Any
    ) -> AsyncIterator[cloud_pb2.ScanSegmentTableResponse]:
        async for response in self._stream(context, segments.scan, request, scopes=(Scope.READ,), entry=True):
            yield response

    # --- opening a segment in the viewer ---------------------------------------------------

    async def GetRrdManifest(
        self, request: cloud_pb2.GetRrdManifestRequest, context: Any
    ) -> AsyncIterator[cloud_pb2.GetRrdManifestResponse]:
        async for response in self._stream(context, manifest.rrd_manifest, request, scopes=(Scope.READ,), entry=True):
            yield response

    async def GetAssetsForSegment(
        self, request: cloud_pb2.GetAssetsForSegmentRequest, context: Any
    ) -> AsyncIterator[cloud_pb2.GetAssetsForSegmentResponse]:
        async for response in self._stream(context, manifest.assets, request, scopes=(Scope.READ,), entry=True):
            yield response

    async def FetchChunks(self, request: cloud_pb2.FetchChunksRequest, context: Any) -> AsyncIterator[bytes]:
        # Serialized FetchChunksResponses around the stored chunk bytes (see add_to_server). No entry
        # header: Rerun's clients send none with this call, so the read scope is what is checked.
        # The next response is read while this one is sent: disk and network both busy, two
        # responses in memory at most.
        try:
            principal = await self._caller(context, Scope.READ)
            made = await asyncio.to_thread(chunks.fetch_chunks, self.depot, principal, request)
            ahead = asyncio.ensure_future(asyncio.to_thread(next, made, None))
            try:
                while (response := await ahead) is not None:
                    ahead = asyncio.ensure_future(asyncio.to_thread(next, made, None))
                    yield response
            finally:
                if not ahead.done():  # the call ended early: let the read under way finish, then drop it
                    await asyncio.wait([ahead])
        except FleetError as exc:
            await _abort(context, exc)
        except grpc.aio.AbortError:
            raise
        except Exception:
            await _internal(context)

    # --- querying from the SDK -------------------------------------------------------------

    async def GetDatasetSchema(
        self, request: cloud_pb2.GetDatasetSchemaRequest, context: Any
    ) -> cloud_pb2.GetDatasetSchemaResponse:
        return await self._unary(context, query.dataset_schema, scopes=(Scope.READ,), entry=True)

    async def FindChunks(
        self, request: cloud_pb2.FindChunksRequest, context: Any
    ) -> AsyncIterator[cloud_pb2.FindChunksResponse]:
        async for response in self._stream(context, query.find_chunks, request, scopes=(Scope.READ,), entry=True):
            yield response

    async def QueryDataset(
        self, request: cloud_pb2.QueryDatasetRequest, context: Any
    ) -> AsyncIterator[cloud_pb2.QueryDatasetResponse]:
        async for response in self._stream(context, query.query_dataset, request, scopes=(Scope.READ,), entry=True):
            yield response


SERVICE_NAME = "rerun.cloud.v1alpha1.RerunCloudService"


class _Handlers:
    """Stands in for a server to take the method handlers the generated code registers."""

    def __init__(self) -> None:
        self.handlers: dict[str, grpc.RpcMethodHandler] = {}

    def add_generic_rpc_handlers(self, handlers: Any) -> None:
        pass

    def add_registered_method_handlers(self, service: str, handlers: dict[str, grpc.RpcMethodHandler]) -> None:
        self.handlers.update(handlers)


OPEN_CALLS = frozenset({"Version"})  # answered without a token, as Rerun's own servers answer them


def _request_name(parse: Callable[[bytes], Message]) -> str:
    owner = getattr(parse, "__self__", None)
    return getattr(owner, "__name__", "request")


def _unimplemented(name: str) -> grpc.RpcMethodHandler:
    """An RPC of the service this depot does not serve: refused before its request is read."""

    async def refuse(request: Any, context: grpc.aio.ServicerContext) -> NoReturn:
        await context.abort(grpc.StatusCode.UNIMPLEMENTED, f"this depot does not serve {name}")
        raise AssertionError("not reached: abort raises")

    return grpc.unary_unary_rpc_method_handler(refuse, request_deserializer=None, response_serializer=None)


def _parsed_after_auth(name: str, handler: grpc.RpcMethodHandler, server: CatalogServer) -> grpc.RpcMethodHandler:
    """`handler`, its request parsed by `server.parsed` (token first, then the protobuf) instead of
    by gRPC, which answers a request that does not parse with UNKNOWN, before any token is read."""
    parse = handler.request_deserializer
    open_call = name in OPEN_CALLS
    if handler.unary_unary is not None:
        unary = handler.unary_unary

        async def unary_call(raw: bytes, context: grpc.aio.ServicerContext) -> Any:
            return await unary(await server.parsed(raw, parse, context, open_call=open_call), context)

        return grpc.unary_unary_rpc_method_handler(unary_call, None, handler.response_serializer)
    streaming = handler.unary_stream

    async def stream_call(raw: bytes, context: grpc.aio.ServicerContext) -> AsyncIterator[Any]:
        async for response in streaming(await server.parsed(raw, parse, context, open_call=open_call), context):
            yield response

    return grpc.unary_stream_rpc_method_handler(stream_call, None, handler.response_serializer)


# Writes to an entry, named by the x-rerun-entry-id header (or by the body's `id`, field 1, for
# the calls of clients from before that header that took one): refused without reading the rest.
WRITE_CALLS = frozenset(
    {
        "DeleteEntry",
        "UpdateEntry",
        "UpdateDatasetEntry",
        "RegisterWithDataset",
        "UnregisterFromDataset",
        "SetSegmentProperties",
        "DeleteSegmentProperties",
        "DoMaintenance",
    }
)
BODY_ID_CALLS = frozenset({"DeleteEntry", "UpdateEntry", "UpdateDatasetEntry"})
STREAMING_CALLS = frozenset({"UnregisterFromDataset"})


def body_entry_id(raw: bytes) -> Tuid | None:
    """The entry a request's `EntryId id = 1` names, if it has one; INVALID_ARGUMENT if malformed."""
    try:
        found = last_field(raw, 1)
        entry = common_pb2.EntryId.FromString(raw[found[1] : found[2]]) if found is not None else None
    except (rrd_errors.RrdError, DecodeError) as exc:
        raise InvalidArgumentError(
            f"the request is not a valid protobuf ({exc}): send it as Rerun's clients do"
        ) from None
    return Tuid.from_proto(entry.id) if entry is not None and entry.HasField("id") else None


def _refused_write(name: str, server: CatalogServer) -> grpc.RpcMethodHandler:
    """A write to an entry: the caller's token checked (read scope: it learns only whether the entry
    is a snapshot version), then refused by `entries.refuse_write`."""

    async def refuse(raw: bytes, context: grpc.aio.ServicerContext) -> NoReturn:
        try:
            principal = await server._caller(context, Scope.READ)
            entry = header_entry_id(context.invocation_metadata())
            if entry is None and name in BODY_ID_CALLS:
                entry = body_entry_id(raw)
            await asyncio.to_thread(entries.refuse_write, server.depot, principal, entry, name)
        except FleetError as exc:
            await _abort(context, exc)
        except grpc.aio.AbortError:
            raise
        except Exception:
            await _internal(context)
        raise AssertionError("not reached: refuse_write raises")

    if name in STREAMING_CALLS:

        async def refuse_stream(raw: bytes, context: grpc.aio.ServicerContext) -> AsyncIterator[bytes]:
            await refuse(raw, context)
            yield b""  # not reached: a generator, as grpc.aio wants of a streaming method

        return grpc.unary_stream_rpc_method_handler(refuse_stream, request_deserializer=None, response_serializer=None)
    return grpc.unary_unary_rpc_method_handler(refuse, request_deserializer=None, response_serializer=None)


def served_handlers(catalog_server: CatalogServer) -> dict[str, grpc.RpcMethodHandler]:
    """Every RPC of the service, by name: those `CatalogServer` answers, each request parsed after
    its token is checked; the others refused as unimplemented without reading them; writes to an
    entry refused (`WRITE_CALLS`). FetchChunks answers bytes it built itself (the stored chunk
    messages, never parsed and serialized again)."""
    taken = _Handlers()
    cloud_pb2_grpc.add_RerunCloudServiceServicer_to_server(catalog_server, taken)  # type: ignore[no-untyped-call]
    generated = dict(taken.handlers)
    generated["FetchChunks"] = grpc.unary_stream_rpc_method_handler(
        catalog_server.FetchChunks,
        request_deserializer=cloud_pb2.FetchChunksRequest.FromString,
        response_serializer=None,
    )
    served = {
        name: _parsed_after_auth(name, handler, catalog_server) if name in vars(CatalogServer) else _unimplemented(name)
        for name, handler in generated.items()
    }
    return {**served, **{name: _refused_write(name, catalog_server) for name in sorted(WRITE_CALLS)}}


def add_to_server(server: grpc.aio.Server, catalog_server: CatalogServer) -> None:
    handlers = served_handlers(catalog_server)
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))
    server.add_registered_method_handlers(SERVICE_NAME, handlers)
