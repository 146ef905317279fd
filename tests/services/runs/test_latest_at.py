"""Latest-at: the scene at a window's start is what the viewer shows at `start` on the whole recording.

The choice of chunks is checked on hand-made chunk entries (ties, sparse components, straddling chunks,
indexes without per-component ranges); the downloads are checked against Rerun's own latest-at (its
chunk store and dataframe reader) on recordings logged by the real SDK with several chunkings, hot and
sealed, and with `rerun rrd verify`.
"""

from __future__ import annotations

import io
import subprocess
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient

from catalog import queries
from catalog.db import session_scope
from services.api.app import create_app
from services.retention.service import PROMOTE, plan, run_plan
from services.runs.latest_at import ChunkEntry, select_chunks
from services.sealed.tiers import Tiers
from services.sealed.write import INDEX
from services.storage.objectstore import open_store
from tests.services.retention import conftest as retention
from tests.services.retention.conftest import Clock, Node, NodeFactory
from tests.services.runs.latest_at_scenes import CHUNKINGS, RECORDING_IDS, latest_at, log_scene

make_node = retention.make_node
PROMOTE_AFTER_S = 600.0
WINDOWS = ((95, 99), (45, 55), (35, 35))


def _entry(
    chunk: str,
    entity: str,
    span: tuple[int, int],
    spans: dict[str, tuple[int, int]] | None,
    components: tuple[str, ...] = (),
) -> ChunkEntry:
    return ChunkEntry(chunk.encode(), entity, False, True, span, spans, components or tuple(spans or ()))


def _select(entries: list[ChunkEntry], lo: int, hi: int, resolve: Any = None) -> tuple[set[str], set[str]]:
    keep, candidates = select_chunks(entries, (lo, hi), True, resolve or (lambda known: known))
    return {k.decode() for k in keep}, {c.decode() for c in candidates}


# --- choosing chunks -------------------------------------------------------------------------------


def test_ties_at_the_newest_time_are_all_kept():
    """Two chunks whose image ends at frame 90 (a tie settled by row id, which only the rows tell)."""
    entries = [
        _entry("a", "/cam", (70, 70), {"img": (70, 70)}),
        _entry("b", "/cam", (90, 90), {"img": (90, 90)}),
        _entry("c", "/cam", (90, 90), {"img": (90, 90)}),
    ]
    assert _select(entries, 95, 99) == ({"b", "c"}, {"b", "c"})


def test_sparse_component_ranges_pick_each_components_own_chunk():
    """Chunk a spans frames 0-80 but has colors only up to 20; chunk b (10-30) has colors at 25."""
    entries = [
        _entry("a", "/robot", (0, 80), {"pos": (0, 80), "colors": (0, 20)}),
        _entry("b", "/robot", (10, 30), {"pos": (10, 30), "colors": (25, 25)}),
    ]
    assert _select(entries, 95, 99)[1] == {"a", "b"}  # a for positions, b for colors
    entries[1] = _entry("b", "/robot", (10, 30), {"pos": (10, 30)})
    assert _select(entries, 95, 99)[1] == {"a"}


def test_a_chunk_straddling_start_is_a_candidate_and_may_make_older_ones_moot():
    straddling = _entry("s", "/straddle", (50, 120), {"pos": (50, 120)})
    assert _select([straddling], 95, 99) == ({"s"}, {"s"})
    older = _entry("o", "/straddle", (10, 40), {"pos": (10, 40)})
    assert _select([older, straddling], 95, 99)[1] == {"s"}  # s has a row at 50 > 40 before start
    tie = _entry("t", "/straddle", (20, 50), {"pos": (20, 50)})
    assert _select([older, tie, straddling], 95, 99)[1] == {"s", "t"}  # 50 == 50: row ids decide


def test_an_index_without_component_ranges_reads_only_the_newest_chunks():
    """Ten chunks of one entity before the window, ranges unknown: read newest first until each
    component's newest end is found and the next chunk cannot hold anything newer."""
    truth = {f"c{i}": _entry(f"c{i}", "/e", (10 * i, 10 * i + 5), {"pos": (10 * i, 10 * i + 5)}) for i in range(10)}
    truth["c9"] = _entry("c9", "/e", (90, 95), {"pos": (90, 95)})  # ...its colors end earlier
    truth["c8"] = _entry("c8", "/e", (80, 85), {"pos": (80, 85), "colors": (80, 80)})
    unknown = [_entry(k, "/e", e.span or (0, 0), None, ("pos", "colors")) for k, e in truth.items()]
    read: list[str] = []

    def resolve(entries: list[ChunkEntry]) -> list[ChunkEntry]:
        read.extend(e.chunk_id.decode() for e in entries)
        return [truth[e.chunk_id.decode()] for e in entries]

    keep, candidates = _select(unknown, 200, 210, resolve)
    assert candidates == {"c9", "c8"} and keep == candidates
    assert read == ["c9", "c8"], read  # c7 ends at 75, before colors' 80: nothing older can matter


# --- against Rerun's own latest-at -------------------------------------------------------------------


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory, rerun_bin: str) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("latest-at")
    return {chunking: log_scene(chunking, root / f"{chunking}.rrd", rerun_bin) for chunking in CHUNKINGS}


@pytest.fixture
def tiers(tmp_path: Path) -> Tiers:
    return Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))


def _promote(node: Node, run_id: str) -> str:
    node.clock.advance(seconds=PROMOTE_AFTER_S + 1)
    outcomes = run_plan(node.retention, plan(node.retention, [PROMOTE]))
    assert outcomes and all(o.ok for o in outcomes), [o.detail for o in outcomes]
    with session_scope(node.catalog) as session:
        life = queries.lifecycle(session, run_id)
        assert life is not None
        return life.prefix


def _drop_component_ranges(tiers: Tiers, prefix: str) -> None:
    """Rewrite the run's chunks.parquet as it was before per-component ranges were kept."""
    key = f"{prefix}/{INDEX}"
    table = pq.read_table(io.BytesIO(tiers.warm.get_range(key))).drop_columns(["component_ranges"])
    out = io.BytesIO()
    pq.write_table(table, out)
    tiers.warm.put(key, out.getvalue())
    assert "component_ranges" not in pq.read_schema(io.BytesIO(tiers.warm.get_range(key))).names


def _answers(client: TestClient, run_id: str, out: Path, tag: str) -> dict[tuple[int, int, bool], Path]:
    answers = {}
    for lo, hi in WINDOWS:
        for exact in (False, True):
            response = client.get(
                f"/v1/runs/{run_id}/recording.rrd",
                params={"timeline": "frame", "start": str(lo), "end": str(hi), "exact": str(exact).lower()},
            )
            assert response.status_code == 200, response.text
            path = out / f"{tag}-{lo}-{hi}-{exact}.rrd"
            path.write_bytes(response.content)
            answers[(lo, hi, exact)] = path
    return answers


def _check(full: Path, answers: dict[tuple[int, int, bool], Path], rerun_bin: str) -> None:
    verify = subprocess.run(
        [rerun_bin, "rrd", "verify", *map(str, answers.values())], capture_output=True, text=True, timeout=120
    )
    assert verify.returncode == 0, verify.stdout + verify.stderr
    for (lo, hi, exact), path in answers.items():
        times = list(range(lo, hi + 1))
        want, got = latest_at(full, times), latest_at(path, times)
        assert any(v is not None for values in want.values() for v in values)  # the oracle sees a scene
        for column, values in want.items():
            assert got.get(column, [None] * len(times)) == values, (path.name, column, exact)


@pytest.mark.sdk
@pytest.mark.parametrize("chunking", CHUNKINGS)
def test_window_answers_equal_rerun_latest_at(
    chunking: str, scenes: dict[str, Path], tiers: Tiers, make_node: NodeFactory, rerun_bin: str, tmp_path: Path
):
    """Hot, sealed, and sealed with an index from before per-component ranges: every windowed download
    (whole chunks or exact) shows at each time of the window what the whole recording shows."""
    node = make_node(tiers, clock=Clock(), promote_after_s=PROMOTE_AFTER_S)
    node.upload(scenes[chunking])
    run_id = RECORDING_IDS["per_call" if chunking == "compacted" else chunking]
    assert list(node.ingest.runs) == [run_id]
    client = TestClient(create_app(node.context, node.ingest, node.retention))
    _check(scenes[chunking], _answers(client, run_id, tmp_path, "hot"), rerun_bin)
    prefix = _promote(node, run_id)
    _check(scenes[chunking], _answers(client, run_id, tmp_path, "warm"), rerun_bin)
    _drop_component_ranges(tiers, prefix)
    _check(scenes[chunking], _answers(client, run_id, tmp_path, "old-index"), rerun_bin)
