"""Redirects stay on the address the client asked: Starlette writes an absolute `Location` from the
request's `Host` header where it redirects by itself (a path with a trailing slash, a static folder
without one). A Host header is the client's to write; a redirect built from a forged one (kept by a
cache, or passed on by a proxy) would send the next reader elsewhere. Such a Location is made a
path on the same origin, which the client resolves against the URL it asked for."""

from __future__ import annotations

from urllib.parse import urlsplit

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send


class SameOriginRedirects:
    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        host = (Headers(scope=scope).get("host") or "").lower()

        async def relative(message: Message) -> None:
            if message["type"] == "http.response.start" and 300 <= message["status"] < 400:
                headers = MutableHeaders(scope=message)
                location = headers.get("location")
                if location is not None:
                    headers["location"] = same_origin(location, host)
            await send(message)

        await self.app(scope, receive, relative)


def same_origin(location: str, host: str) -> str:
    """`location` as a path when it names the request's own host (as the Host header said it);
    any other Location as it is."""
    parts = urlsplit(location)
    if not parts.netloc or parts.netloc.lower() != host:
        return location
    path = "/" + parts.path.lstrip("/")  # one slash: "//name" would be another host again
    return path + (f"?{parts.query}" if parts.query else "")
