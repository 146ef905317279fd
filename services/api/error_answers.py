"""How the REST app answers an error: a `FleetError` with its own status and body, a bad
parameter as INVALID_ARGUMENT naming it, a catalog that does not answer as a retryable 503."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from core.errors import CATALOG_DOWN, CatalogUnavailableError, ErrorCode, FleetError, http_status


async def _bad_parameter(_: Request, exc: RequestValidationError) -> JSONResponse:
    problems = "; ".join(f"parameter {e['loc'][-1]!r}: {e['msg']}" for e in exc.errors())
    return JSONResponse(
        {"code": ErrorCode.INVALID_ARGUMENT.value, "message": problems},
        status_code=http_status(ErrorCode.INVALID_ARGUMENT),
    )


async def _fleet_error(_: Request, exc: FleetError) -> JSONResponse:
    return JSONResponse(exc.to_dict(), status_code=exc.http_status(), headers=exc.headers())


async def _catalog_down(_: Request, exc: Exception) -> JSONResponse:
    # The database did not answer (down, restarting, overloaded): not the caller's mistake.
    error = CatalogUnavailableError()
    return JSONResponse(error.to_dict(), status_code=error.http_status())


def install(app: FastAPI) -> None:
    app.exception_handler(RequestValidationError)(_bad_parameter)
    app.exception_handler(FleetError)(_fleet_error)
    for catalog_down in CATALOG_DOWN:
        app.exception_handler(catalog_down)(_catalog_down)
