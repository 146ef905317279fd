"""How the REST app answers an error: a `FleetError` with its own status and body, a bad
parameter as INVALID_ARGUMENT naming it, a catalog that does not answer as a retryable 503, and
what the framework refuses before a handler runs (no such route, a body that does not parse) with
its status and the same {code, message} body."""

from __future__ import annotations

from collections.abc import Sequence

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as FrameworkError

from core.errors import CATALOG_DOWN, CatalogUnavailableError, ErrorCode, FleetError, http_status


async def _bad_parameter(_: Request, exc: RequestValidationError) -> JSONResponse:
    problems = "; ".join(f"parameter {_named(e['loc'])!r}: {e['msg']}" for e in exc.errors())
    return JSONResponse(
        {"code": ErrorCode.INVALID_ARGUMENT.value, "message": problems},
        status_code=http_status(ErrorCode.INVALID_ARGUMENT),
    )


def _named(loc: Sequence[str | int]) -> str | int:
    """The parameter a problem is of: its name (`bytes`), or its path in a body of nested objects
    (`event.start`, `window.include[0]`)."""
    path = list(loc[1:]) if len(loc) > 1 and loc[0] in ("body", "query", "path", "header", "cookie") else list(loc)
    if len(path) == 1:
        return path[0]
    named = ""
    for part in path:
        named += f"[{part}]" if isinstance(part, int) else (f".{part}" if named else str(part))
    return named or str(loc[-1])


async def _fleet_error(_: Request, exc: FleetError) -> JSONResponse:
    return JSONResponse(exc.to_dict(), status_code=exc.http_status(), headers=exc.headers())


async def _catalog_down(_: Request, exc: Exception) -> JSONResponse:
    # The database did not answer (down, restarting, overloaded): not the caller's mistake.
    error = CatalogUnavailableError()
    return JSONResponse(error.to_dict(), status_code=error.http_status())


_FRAMEWORK_CODES = {
    401: ErrorCode.UNAUTHENTICATED,
    403: ErrorCode.PERMISSION_DENIED,
    404: ErrorCode.NOT_FOUND,
    413: ErrorCode.MESSAGE_TOO_LARGE,
}
_FRAMEWORK_HINTS = {
    400: "send a body of the form the route takes (UTF-8 JSON unless it says otherwise; see /docs)",
    404: "no such route (see /docs)",
    405: "a method this path does not take (see /docs)",
}


async def _framework_error(request: Request, exc: FrameworkError) -> JSONResponse:
    status = exc.status_code
    code = _FRAMEWORK_CODES.get(status, ErrorCode.INVALID_ARGUMENT if status < 500 else ErrorCode.INTERNAL)
    where = f"{request.method} {request.url.path[:200]}"
    hint = _FRAMEWORK_HINTS.get(status)
    message = f"{where}: {exc.detail}" + (f": {hint}" if hint else "")
    return JSONResponse({"code": code.value, "message": message}, status_code=status, headers=exc.headers)


def install(app: FastAPI) -> None:
    app.exception_handler(RequestValidationError)(_bad_parameter)
    app.exception_handler(FrameworkError)(_framework_error)
    app.exception_handler(FleetError)(_fleet_error)
    for catalog_down in CATALOG_DOWN:
        app.exception_handler(catalog_down)(_catalog_down)
