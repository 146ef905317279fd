"""The one error hierarchy of the service, and the one table mapping its codes to HTTP and gRPC.

Every error a user can see is a `FleetError` with an `ErrorCode`; REST and gRPC handlers map
it through `http_status()` / `grpc_status()` and nowhere else.
"""

from __future__ import annotations

import enum
import functools
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import sqlalchemy.exc as sa_exc

    CatalogDown = tuple[type[sa_exc.OperationalError], type[sa_exc.InterfaceError], type[sa_exc.TimeoutError]]
    # Errors of the catalog database itself (down, restarting, overloaded, past its statement or
    # connect deadline: Postgres' QueryCanceled is an OperationalError), as opposed to a record it
    # refuses. Not the caller's mistake nor a fault of the depot: UNAVAILABLE on every surface.
    # Made on first use (`__getattr__` below): a CLI command that never opens a catalog does not
    # load SQLAlchemy.
    CATALOG_DOWN: CatalogDown


class ErrorCode(enum.Enum):
    INVALID_ARGUMENT = "INVALID_ARGUMENT"
    INVALID_RRD = "INVALID_RRD"
    INVALID_MCAP = "INVALID_MCAP"
    CONVERSION_LIMIT = "CONVERSION_LIMIT"
    UNSUPPORTED_RRD_VERSION = "UNSUPPORTED_RRD_VERSION"
    MESSAGE_TOO_LARGE = "MESSAGE_TOO_LARGE"
    NOT_FOUND = "NOT_FOUND"
    ALREADY_EXISTS = "ALREADY_EXISTS"
    CONFLICT = "CONFLICT"
    GONE = "GONE"
    INVALID_SQL = "INVALID_SQL"
    SQL_NOT_ALLOWED = "SQL_NOT_ALLOWED"
    QUERY_TIMEOUT = "QUERY_TIMEOUT"
    RESULT_TOO_LARGE = "RESULT_TOO_LARGE"
    QUERY_OUT_OF_MEMORY = "QUERY_OUT_OF_MEMORY"
    UNAUTHENTICATED = "UNAUTHENTICATED"
    PERMISSION_DENIED = "PERMISSION_DENIED"
    RESOURCE_EXHAUSTED = "RESOURCE_EXHAUSTED"
    INSUFFICIENT_STORAGE = "INSUFFICIENT_STORAGE"
    UNAVAILABLE = "UNAVAILABLE"
    UNIMPLEMENTED = "UNIMPLEMENTED"
    INTERNAL = "INTERNAL"


# code -> (HTTP status, gRPC status code name). The only place statuses are chosen.
_STATUS: dict[ErrorCode, tuple[int, str]] = {
    ErrorCode.INVALID_ARGUMENT: (422, "INVALID_ARGUMENT"),
    ErrorCode.INVALID_RRD: (400, "INVALID_ARGUMENT"),
    ErrorCode.INVALID_MCAP: (400, "INVALID_ARGUMENT"),
    ErrorCode.CONVERSION_LIMIT: (413, "RESOURCE_EXHAUSTED"),
    ErrorCode.UNSUPPORTED_RRD_VERSION: (400, "INVALID_ARGUMENT"),
    ErrorCode.MESSAGE_TOO_LARGE: (413, "RESOURCE_EXHAUSTED"),
    ErrorCode.NOT_FOUND: (404, "NOT_FOUND"),
    ErrorCode.ALREADY_EXISTS: (409, "ALREADY_EXISTS"),
    ErrorCode.CONFLICT: (409, "FAILED_PRECONDITION"),
    ErrorCode.GONE: (410, "NOT_FOUND"),
    ErrorCode.INVALID_SQL: (400, "INVALID_ARGUMENT"),
    ErrorCode.SQL_NOT_ALLOWED: (400, "PERMISSION_DENIED"),
    ErrorCode.QUERY_TIMEOUT: (408, "DEADLINE_EXCEEDED"),
    ErrorCode.RESULT_TOO_LARGE: (413, "RESOURCE_EXHAUSTED"),
    ErrorCode.QUERY_OUT_OF_MEMORY: (413, "RESOURCE_EXHAUSTED"),
    ErrorCode.UNAUTHENTICATED: (401, "UNAUTHENTICATED"),
    ErrorCode.PERMISSION_DENIED: (403, "PERMISSION_DENIED"),
    ErrorCode.RESOURCE_EXHAUSTED: (429, "RESOURCE_EXHAUSTED"),
    ErrorCode.INSUFFICIENT_STORAGE: (507, "RESOURCE_EXHAUSTED"),
    ErrorCode.UNAVAILABLE: (503, "UNAVAILABLE"),
    ErrorCode.UNIMPLEMENTED: (501, "UNIMPLEMENTED"),
    ErrorCode.INTERNAL: (500, "INTERNAL"),
}


class FleetError(Exception):
    """Base of every error the service reports to a user."""

    code: ErrorCode = ErrorCode.INTERNAL

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message

    def http_status(self) -> int:
        return http_status(self.code)

    def grpc_status(self) -> str:
        return grpc_status(self.code)

    def to_dict(self) -> dict[str, str]:
        return {"code": self.code.value, "message": self.message}

    def headers(self) -> dict[str, str]:
        """HTTP headers the answer carries besides its status (a challenge, a time to retry)."""
        return {}


def http_status(code: ErrorCode) -> int:
    return _STATUS[code][0]


def grpc_status(code: ErrorCode) -> str:
    """The name of the `grpc.StatusCode` member for `code`."""
    return _STATUS[code][1]


# One class per code: what a caller may catch or a test may expect. A few errors that callers
# catch on their own (an object not found in a store, a store that failed, an unsafe id, SQL workers
# busy, codec errors) keep classes of their own, under FleetError.
class InvalidArgumentError(FleetError):
    code = ErrorCode.INVALID_ARGUMENT


class InvalidRulesError(InvalidArgumentError):
    """A rules file refused whole: every problem found, each naming its line and field."""

    def __init__(self, problems: list[dict[str, object]]) -> None:
        lines = "; ".join(
            f"line {p['line']}: {p['field']}: {p['message']}" if p.get("line") else f"{p['field']}: {p['message']}"
            for p in problems
        )
        super().__init__(f"the rules file has {len(problems)} problem(s), nothing was applied: {lines}")
        self.problems = problems

    def to_dict(self) -> dict[str, str]:
        answer: dict[str, object] = {**super().to_dict(), "problems": self.problems}
        return answer  # type: ignore[return-value]


class InvalidMcapError(FleetError):
    """An MCAP upload the depot cannot read or the Rerun CLI cannot convert."""

    code = ErrorCode.INVALID_MCAP


class ConversionLimitError(FleetError):
    """A conversion that went past its time, memory or output limit."""

    code = ErrorCode.CONVERSION_LIMIT


class NotFoundError(FleetError):
    code = ErrorCode.NOT_FOUND


class ConflictError(FleetError):
    code = ErrorCode.CONFLICT


class AlreadyExistsError(FleetError):
    code = ErrorCode.ALREADY_EXISTS


class GoneError(FleetError):
    code = ErrorCode.GONE


class InvalidSqlError(FleetError):
    code = ErrorCode.INVALID_SQL


class SqlNotAllowedError(FleetError):
    code = ErrorCode.SQL_NOT_ALLOWED


class QueryTimeoutError(FleetError):
    code = ErrorCode.QUERY_TIMEOUT


class ResultTooLargeError(FleetError):
    code = ErrorCode.RESULT_TOO_LARGE


class QueryOutOfMemoryError(FleetError):
    code = ErrorCode.QUERY_OUT_OF_MEMORY


class InsufficientStorageError(FleetError):
    code = ErrorCode.INSUFFICIENT_STORAGE


class ResourceExhaustedError(FleetError):
    code = ErrorCode.RESOURCE_EXHAUSTED


class RateLimitedError(ResourceExhaustedError):
    """Too many requests of one kind from one token: retry after `retry_after_s` seconds."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = max(1, retry_after_s)

    def headers(self) -> dict[str, str]:
        return {"Retry-After": str(self.retry_after_s)}


class UnauthenticatedError(FleetError):
    """No token, or one this depot does not accept (malformed, not signed here, expired, revoked)."""

    code = ErrorCode.UNAUTHENTICATED

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason  # missing | invalid | expired | revoked: counted in /metrics

    def headers(self) -> dict[str, str]:
        return {"WWW-Authenticate": 'Bearer realm="fleet-telemetry"'}


class PermissionDeniedError(FleetError):
    """A valid token without the scope an action needs, or a robot's token used for another robot."""

    code = ErrorCode.PERMISSION_DENIED


class UnavailableError(FleetError):
    code = ErrorCode.UNAVAILABLE


@functools.cache
def _catalog_down() -> CatalogDown:
    import sqlalchemy.exc as sa_exc

    return (sa_exc.OperationalError, sa_exc.InterfaceError, sa_exc.TimeoutError)


def __getattr__(name: str) -> object:
    """CATALOG_DOWN, made on first use (module attribute lookup, PEP 562)."""
    if name == "CATALOG_DOWN":
        return _catalog_down()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class CatalogUnavailableError(UnavailableError):
    def __init__(self, message: str = "the catalog database is unavailable right now: retry in a moment") -> None:
        super().__init__(message)


def as_fleet_error(exc: BaseException) -> FleetError | None:
    """What a user is told of `exc`: itself if it is one of ours, UNAVAILABLE for a catalog that did
    not answer, None for anything else (a fault of the depot, answered INTERNAL)."""
    if isinstance(exc, FleetError):
        return exc
    if isinstance(exc, _catalog_down()):
        return CatalogUnavailableError()
    return None


class OwnerDownError(UnavailableError):
    """A run whose data is hot on another node of the depot, its owner, which has stopped answering:
    the run is there, not missing (a 404 would say it does not exist)."""

    def __init__(self, run_id: str, node_id: str, peer_addr: str) -> None:
        super().__init__(
            f"run {run_id} is held by node {node_id} ({peer_addr}), which owns it and has stopped answering: "
            "its data is there; try again once that node is back"
        )
        self.node_id, self.peer_addr = node_id, peer_addr

    def to_dict(self) -> dict[str, str]:
        return {**super().to_dict(), "owner": self.node_id, "owner_addr": self.peer_addr}

    def headers(self) -> dict[str, str]:
        return {"Retry-After": "30"}


class UnimplementedError(FleetError):
    """A call this depot does not answer (a part of a client protocol it leaves out)."""

    code = ErrorCode.UNIMPLEMENTED


class InternalError(FleetError):
    code = ErrorCode.INTERNAL


class BadParameterError(InvalidArgumentError):
    """A request parameter that is not acceptable, named, with what would be."""

    code = ErrorCode.INVALID_ARGUMENT

    def __init__(self, name: str, problem: str) -> None:
        super().__init__(f"parameter {name!r}: {problem}")
        self.parameter, self.problem = name, problem

    def within(self, part: str) -> BadParameterError:
        """The same problem, named as a field of `part` of the request (`event.start`)."""
        return BadParameterError(f"{part}.{self.parameter}", self.problem)
