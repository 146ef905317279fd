"""A depot with auth on (the app as `fleet serve` wires it, on DuckDB and Postgres) fed small
synthetic recordings, hot or sealed, with people's events on them; and an independent answer to
which chunks an episode reads, worked out from the recording's own chunks."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from sdk_client.rest import FleetClient
from services.rrd import ArrowMessage
from services.rrd.chunk import chunk_meta
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.corpus.conftest import sdk
from tests.services.rrd.synthetic import recording_bytes, recording_events

ROBOT = "robot-7"

__all__ = ["ROBOT", "Depot", "sdk"]


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url) as opened:
        yield opened


def upload(depot: Depot, run_id: str, *, chunks: int = 12, robot: str = ROBOT, seal: bool = False) -> bytes:
    """A synthetic recording (`run_id` its recording id, so its run id) uploaded by its robot; with
    `seal`, promoted to the warm tier. Its bytes."""
    data = recording_bytes(run_id, chunks)
    answer = depot.client.post("/v1/uploads", content=data, headers=bearer(depot.token("ingest", robot=robot)))
    assert answer.status_code == 200 and answer.json()["runs"] == [run_id], answer.text
    if seal:
        sealed = depot.client.post(f"/v1/runs/{run_id}/promote", headers=bearer(depot.token("write")))
        assert sealed.status_code == 200 and sealed.json()["tier"] == "warm", sealed.text
    return data


def writer(depot: Depot) -> FleetClient:
    return sdk(depot, depot.token("write", name="alice"))


def _matches(pattern: str, path: str) -> bool:
    if pattern.endswith("/**"):
        root = pattern[:-3].rstrip("/")
        return path == (root or "/") or path.startswith(root + "/")
    return path == pattern


def expected_chunks(
    data: bytes,
    tmp_path: Path,
    include: list[str],
    window: tuple[int, int] | None = None,
    exclude: tuple[str, ...] = (),
) -> list[str]:
    """The chunk ids (hex, sorted) an episode of this recording reads, worked out here from its
    chunks' own `frame` ranges: the entities' chunks (whole run), or the static ones, those
    overlapping the window, and per entity the one ending last before the window's start (the
    synthetic chunks hold one component each, so that is the latest-at candidate)."""
    path = tmp_path / f"oracle-{len(data)}-{hash(data)}.rrd"
    path.write_bytes(data)
    metas = [chunk_meta(e) for e in recording_events(path) if isinstance(e, ArrowMessage)]
    chosen = [
        m
        for m in metas
        if any(_matches(p, m.entity_path) for p in include) and not any(_matches(p, m.entity_path) for p in exclude)
    ]
    if window is None:
        return sorted(m.chunk_id.hex() for m in chosen)
    lo, hi = window
    kept = set()
    newest_before: dict[str, tuple[int, bytes]] = {}
    for m in chosen:
        span = next(((t.range.min, t.range.max) for t in m.timelines if t.name == "frame"), None)
        if m.is_static:
            kept.add(m.chunk_id)
        elif span is not None:
            if span[1] >= lo and span[0] <= hi:
                kept.add(m.chunk_id)
            if span[1] < lo and span[1] >= newest_before.get(m.entity_path, (-1, b""))[0]:
                newest_before[m.entity_path] = (span[1], m.chunk_id)
    kept |= {chunk_id for _, chunk_id in newest_before.values()}
    return sorted(c.hex() for c in kept)
