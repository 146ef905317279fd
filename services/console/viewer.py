"""The Rerun web viewer in the browser, served by the depot itself from the installed
`rerun-notebook` package (the viewer's JavaScript and WebAssembly of the pinned Rerun version):
`/console/runs/{run}/viewer` opens the run in it by a signed link; without the package, the page
explains `rerun --serve-web` instead."""

from __future__ import annotations

import importlib.metadata
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

from fastapi import Query, Request
from fastapi.responses import FileResponse, HTMLResponse, Response

from core.errors import GoneError, NotFoundError
from core.states import Tier
from services.console.run import public_base, signed_link
from services.console.web import Viewer, console_router, render
from services.runs import service as runs_service
from services.runs.download import window_from_query

router = console_router()

PACKAGE = "rerun_notebook"
ASSETS = {
    "widget.js": "text/javascript; charset=utf-8",
    "re_viewer_bg.wasm": "application/wasm",
    "widget.css": "text/css; charset=utf-8",
}
# The viewer's page only: the console's policy plus WebAssembly compiled from the depot's own file
# ('wasm-unsafe-eval' allows compiling WebAssembly, not JavaScript eval).
VIEWER_CSP = (
    "default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data: blob:; connect-src 'self'; worker-src 'self' blob:; frame-ancestors 'none'; "
    "base-uri 'self'; form-action 'self'"
)
# The assets' URL names their version: a new version is a new URL, so browsers may keep them long.
ASSET_CACHE = "private, max-age=31536000, immutable"


@dataclass(frozen=True)
class ViewerAssets:
    version: str
    folder: Path

    def path(self, name: str) -> Path:
        return self.folder / name


def viewer_assets(package: str = PACKAGE) -> ViewerAssets | None:
    """The installed web viewer's files (`widget.js`, `re_viewer_bg.wasm`), or None if the package
    is not installed or lacks them."""
    try:
        folder = resources.files(package) / "static"
        version = importlib.metadata.version(package)
    except (ModuleNotFoundError, importlib.metadata.PackageNotFoundError):
        return None
    path = Path(str(folder))
    if not all((path / name).is_file() for name in ("widget.js", "re_viewer_bg.wasm")):
        return None
    return ViewerAssets(version, path)


@router.get("/runs/{run_id}/viewer")
def viewer_page(
    request: Request,
    run_id: str,
    principal: Viewer,
    timeline: Annotated[str | None, Query()] = None,
    start: Annotated[str | None, Query()] = None,
    end: Annotated[str | None, Query()] = None,
) -> HTMLResponse:
    """The run in the web viewer; with `timeline`, `start`, `end` only that window of it (an
    event's link: the recording's link is signed with the window)."""
    answer = runs_service.run_answer(
        request.app.state.catalog,
        run_id,
        None,
        runs_service.hot_lookup(request.app.state.ingest, request.app.state.node.default_robot),
    )
    if answer["tier"] == Tier.DELETED:
        raise GoneError(f"run {run_id!r} is deleted: there is nothing to open")
    # The viewer fetches the recording from this page's own origin (the policy's connect-src 'self'):
    # its link is a path, made absolute by the page's script; the `rerun` command beside it uses the
    # depot's public address.
    window = window_params(answer, timeline, start, end)
    viewer_url = signed_link(request, principal, run_id, window, "")
    command_url = signed_link(request, principal, run_id, window, public_base(request))
    assets = viewer_assets()
    response = render(
        request,
        "viewer.html",
        principal,
        run=answer,
        assets=assets,
        viewer_url=viewer_url,
        command_url=command_url,
        window=dict(window),
        window_type=next((t["type"] for t in answer["timelines"] if t["name"] == timeline), None),
    )
    response.headers["content-security-policy"] = VIEWER_CSP  # before the console's default is set
    return response


def window_params(
    answer: dict[str, Any], timeline: str | None, start: str | None, end: str | None
) -> list[tuple[str, str]]:
    """The recording's window parameters, checked against the run's timelines (a bad one is the
    page's 422, not a viewer that fails to load)."""
    types = {t["name"]: t["type"] for t in answer["timelines"]}
    window_from_query(types, timeline or None, start or None, end or None, latest_at=True)
    given = (("timeline", timeline), ("start", start), ("end", end))
    return [(name, value) for name, value in given if value]


@router.get("/viewer-assets/{version}/{name}")
def viewer_asset(request: Request, version: str, name: str, _: Viewer) -> Response:
    """The web viewer's files, of the installed version only."""
    assets = viewer_assets()
    if assets is None:
        raise NotFoundError(
            f"the Rerun web viewer is not installed on this depot: pip install {PACKAGE.replace('_', '-')}"
        )
    if version != assets.version or name not in ASSETS:
        raise NotFoundError(f"no viewer file {version}/{name}: this depot serves version {assets.version}")
    return FileResponse(
        assets.path(name),
        media_type=ASSETS[name],
        headers={"cache-control": ASSET_CACHE},
    )
