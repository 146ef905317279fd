"""The console's dataset snapshot pages ([datasets.md](../../docs/datasets.md)), read from the service
functions `GET /v1/datasets...` answers with:

- `/console/datasets`: every snapshot with its latest version;
- `/console/datasets/NAME`: its versions, newest first;
- `/console/datasets/NAME/N`: one version: its summary, its selection, the runs it skipped (with
  why), and its episodes a page at a time (by the cursor the REST answer gives), each linking to its
  run and its event and opening the web viewer at its window (a whole-run episode: the run).

An unknown name or version is the console's 404 page; a cursor of another version is said on the
version's page. A version's page lists its export jobs with their progress, and each episode's
quality flags as the latest export of the version that ended reported them."""

from __future__ import annotations

import json
import re
from typing import Any
from urllib.parse import quote, urlencode

from fastapi import Request
from fastapi.responses import HTMLResponse

from catalog.db import session_scope
from catalog.queries import timeline_types
from core.errors import InvalidArgumentError, NotFoundError
from services.console.run_corpus import window_href
from services.console.web import PREFIX, Viewer, console_router, render
from services.datasets import exports, service
from services.datasets.rest import MAX_VERSION, sources

router = console_router()
JOBS_SHOWN = 20  # export jobs of a version listed on its page
PAGE = 50  # episodes on a page of a version's page
VERSION = re.compile(r"[0-9]{1,19}")


def dataset_href(name: str, version: int | None = None, cursor: str | None = None) -> str:
    """A snapshot's page, a version's, or a page of its episodes."""
    href = f"{PREFIX}/datasets/{quote(name, safe='')}"
    if version is not None:
        href += f"/{version}"
    return href + (f"?{urlencode({'cursor': cursor})}" if cursor else "")


def run_href(run_id: str) -> str:
    return f"{PREFIX}/runs/{quote(run_id, safe='')}"


@router.get("/datasets")
def datasets_page(request: Request, principal: Viewer) -> HTMLResponse:
    answer = service.datasets_answer(sources(request))
    return render(request, "datasets.html", principal, datasets=answer["datasets"], dataset_href=dataset_href)


@router.get("/datasets/{name}")
def dataset_page(request: Request, name: str, principal: Viewer) -> HTMLResponse:
    answer = service.dataset_answer(sources(request), name)
    return render(request, "dataset.html", principal, dataset=answer, dataset_href=dataset_href)


@router.get("/datasets/{name}/{version}")
def version_page(request: Request, name: str, version: str, principal: Viewer) -> HTMLResponse:
    number = version_number(name, version)
    cursor = (request.query_params.get("cursor") or "").strip() or None
    found = sources(request)
    problem, status = None, 200
    try:
        answer = service.version_answer(found, name, number, PAGE, cursor)
    except InvalidArgumentError as exc:
        if cursor is None:
            raise
        # A cursor of another version (or none at all): the version is shown, its episodes are not.
        answer = {**service.version_answer(found, name, number, PAGE), "episodes_page": [], "next_cursor": None}
        problem, status = exc.message, exc.http_status()
    jobs = exports.jobs_answer(found, f"{name}@{number}", JOBS_SHOWN)["exports"]
    flags = quality_of(jobs)
    episodes = [{**e, "flags": flags.get(e["index"], [])} for e in episode_views(request, answer["episodes_page"])]
    next_cursor = answer["next_cursor"]
    return render(
        request,
        "dataset_version.html",
        principal,
        status=status,
        v=answer,
        selection=json.dumps(answer["selection"], indent=2, sort_keys=True, ensure_ascii=False),
        episodes=episodes,
        next_href=dataset_href(name, number, next_cursor) if next_cursor else None,
        first_href=dataset_href(name, number) if cursor else None,
        problem=problem,
        jobs=jobs,
        checked_by=next((j["id"] for j in jobs if j["state"] in ("done", "failed")), None),
        dataset_href=dataset_href,
        run_href=run_href,
    )


def quality_of(jobs: list[dict[str, Any]]) -> dict[int, list[dict[str, Any]]]:
    """Each episode's quality flags, as the latest export of the version that ended reported them."""
    for job in jobs:  # newest first
        if job["state"] in ("done", "failed"):
            return {int(r["episode"]): r["flags"] for r in job["report"]}
    return {}


def version_number(name: str, text: str) -> int:
    """The version the URL names; a 404 for what is no version number (as for a version not written)."""
    if VERSION.fullmatch(text) and 1 <= int(text) <= MAX_VERSION:
        return int(text)
    shown = text if len(text) <= 40 else text[:40] + "..."
    raise NotFoundError(f"dataset {name!r} has no version {shown!r}: versions are numbered {name}@1, {name}@2, ...")


def episode_views(request: Request, episodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each episode as the REST answer gives it, with what the page adds: its timeline's type (its
    window written as times on a timestamp timeline; None once its run is gone from the catalog),
    the viewer at its window (None for a missing run) and its event on the run's page."""
    if not episodes:
        return []
    with session_scope(request.app.state.catalog) as session:
        types = timeline_types(session, {e["run_id"] for e in episodes})
    return [
        {
            **e,
            "timeline_type": types.get((e["run_id"], e["timeline"])),
            "viewer_href": None if e["missing"] else window_href(e["run_id"], e["timeline"], e["start"], e["end"]),
            "event_href": f"{run_href(e['run_id'])}#event-{quote(e['event_id'], safe='')}" if e["event_id"] else None,
        }
        for e in episodes
    ]
