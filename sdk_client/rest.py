"""REST client of the fleet service (what `fleet upload`, `fleet runs ...` use)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

from services.errors import ErrorCode, FleetError

UPLOAD_PIECE = 1024 * 1024


class ServiceError(FleetError):
    """The service answered with an error; `status` is the HTTP status, `body` its JSON."""

    def __init__(self, message: str, status: int, body: dict[str, Any]) -> None:
        super().__init__(message)
        self.status = status
        self.body = body
        try:
            self.code = ErrorCode(body.get("code", "INTERNAL"))
        except ValueError:
            self.code = ErrorCode.INTERNAL


class UnreachableError(FleetError):
    code = ErrorCode.UNAVAILABLE


class FleetClient:
    def __init__(self, api_url: str, *, timeout: float = 300.0) -> None:
        self.api_url = api_url.rstrip("/")
        self._http = httpx.Client(base_url=self.api_url, timeout=timeout)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> FleetClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def upload(self, path: Path, on_progress: Callable[[int], None] | None = None) -> dict[str, Any]:
        """Stream an .rrd file to `POST /v1/uploads` (constant memory); returns the service's report."""

        def pieces() -> Iterator[bytes]:
            with open(path, "rb") as fh:
                while piece := fh.read(UPLOAD_PIECE):
                    yield piece
                    if on_progress is not None:
                        on_progress(len(piece))

        return self._request("POST", "/v1/uploads", content=pieces(),
                             headers={"Content-Type": "application/vnd.rerun.rrd"})

    def _request(self, method: str, url: str, **kwargs: Any) -> dict[str, Any]:
        try:
            response = self._http.request(method, url, **kwargs)
        except httpx.TransportError as exc:
            raise UnreachableError(f"cannot reach the fleet service at {self.api_url} ({exc}); "
                                   "is it running? set FLEET_API_URL") from exc
        body: dict[str, Any]
        try:
            body = response.json()
        except ValueError:
            body = {"message": response.text[:500]}
        if response.status_code >= 400:
            raise ServiceError(str(body.get("message", response.reason_phrase)), response.status_code, body)
        return body
