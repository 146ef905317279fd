"""Downloads the real Rerun tools accept: whole runs, entity filters, and the viewer's own loader."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk
NAMES = ("points", "blueprint", "transforms")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]) -> Iterator[LiveServer]:
    live = LiveServer(Path(tmp_path_factory.mktemp("download")) / "data").start()
    for name in NAMES:
        assert httpx.post(f"{live.url}/v1/uploads", content=recordings[name].data, timeout=60).status_code == 200
    yield live
    live.stop()


def _download(server: LiveServer, run_id: str, out: Path, **params: object) -> httpx.Response:
    response = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", params=params,  # type: ignore[arg-type]
                         headers={"Origin": "http://localhost:9090"}, timeout=120)  # as a browser viewer asks
    out.write_bytes(response.content)
    return response


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(args), capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("name", NAMES)
def test_full_download_equals_the_original(server: LiveServer, recordings: dict[str, Recording], name: str,
                                           rerun_bin: str, tmp_path: Path):
    rec = recordings[name]
    out = tmp_path / "run.rrd"
    response = _download(server, rec.recordings[0]["recording_id"], out)
    assert response.status_code == 200
    assert response.headers["content-disposition"] == f'attachment; filename="{rec.recordings[0]["recording_id"]}.rrd"'
    assert response.headers["etag"] and response.headers["access-control-allow-origin"] == "*"
    verify = _run(rerun_bin, "rrd", "verify", str(out))  # footers checked
    assert verify.returncode == 0, verify.stderr
    compare = _run(rerun_bin, "rrd", "compare", "--unordered", str(rec.path), str(out))
    assert compare.returncode == 0, compare.stdout + compare.stderr


def test_entity_filter_equals_rerun_rrd_filter(server: LiveServer, recordings: dict[str, Recording], rerun_bin: str,
                                               tmp_path: Path):
    rec = recordings["transforms"]
    entities = sorted(rec.recordings[0]["entities"])
    dropped = next(e for e in entities if not e.startswith("/__properties"))
    ours = tmp_path / "ours.rrd"
    assert _download(server, rec.recordings[0]["recording_id"], ours, exclude=dropped).status_code == 200
    theirs = tmp_path / "theirs.rrd"
    assert _run(rerun_bin, "rrd", "filter", "--drop-entity", dropped, str(rec.path), "-o", str(theirs)).returncode == 0
    assert _run(rerun_bin, "rrd", "verify", str(ours)).returncode == 0
    compare = _run(rerun_bin, "rrd", "compare", "--unordered", str(theirs), str(ours))
    assert compare.returncode == 0, compare.stdout + compare.stderr


def test_include_subtree_and_exclude_wins(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path):
    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    all_paths = set(rec.recordings[0]["entities"])
    out = tmp_path / "sub.rrd"
    assert _download(server, run_id, out, include="/world/**").status_code == 200
    got = {chunk_meta(e).entity_path for e in iter_events(out)
           if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING}
    assert got == {p for p in all_paths if p == "/world" or p.startswith("/world/")} and got
    excluded = sorted(got)[0]
    _download(server, run_id, out, include="/world/**", exclude=excluded)
    assert excluded not in {chunk_meta(e).entity_path for e in iter_events(out) if isinstance(e, ArrowMessage)}


def test_blueprint_can_be_left_out(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path):
    run_id = recordings["blueprint"].recordings[0]["recording_id"]
    out = tmp_path / "nobp.rrd"
    _download(server, run_id, out, blueprint="false")
    kinds = {e.store_id.kind for e in iter_events(out) if isinstance(e, ArrowMessage)}
    assert kinds == {StoreKind.RECORDING}


def test_the_viewer_loader_saves_the_same(server: LiveServer, recordings: dict[str, Recording], rerun_bin: str,
                                          tmp_path: Path):
    run_id = recordings["points"].recordings[0]["recording_id"]
    url = f"{server.url}/v1/runs/{run_id}/recording.rrd"
    saved = tmp_path / "saved.rrd"
    result = _run(rerun_bin, "--save", str(saved), url)
    assert result.returncode == 0, result.stderr
    ours = tmp_path / "ours.rrd"
    _download(server, run_id, ours)
    compare = _run(rerun_bin, "rrd", "compare", "--unordered", str(ours), str(saved))
    assert compare.returncode == 0, compare.stdout + compare.stderr


def test_errors(server: LiveServer):
    missing = httpx.get(f"{server.url}/v1/runs/nope/recording.rrd", timeout=30)
    assert missing.status_code == 404 and "nope" in missing.json()["message"]
    bad = httpx.get(f"{server.url}/v1/runs/nope/recording.rrd", params={"include": "world"}, timeout=30)
    assert bad.status_code == 422 and "'include'" in bad.json()["message"]


def _recording_chunks(path: Path) -> dict[bytes, object]:
    return {e.chunk_id: chunk_meta(e) for e in iter_events(path)  # type: ignore[misc]
            if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING}


@pytest.mark.parametrize(("timeline", "start", "end", "lo", "hi"), [
    ("frame", "104", "105", 104, 105),
    ("sim", "0.75s", "1s", 750_000_000, 1_000_000_000),
])
def test_time_window(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path, rerun_bin: str,
                     timeline: str, start: str, end: str, lo: int, hi: int):
    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    original = _recording_chunks(rec.path)

    def window_range(meta: object) -> tuple[int, int] | None:
        tl = next((t for t in meta.timelines if t.name == timeline), None)  # type: ignore[attr-defined]
        return None if tl is None else (tl.range.min, tl.range.max)

    overlapping = {cid for cid, m in original.items()
                   if (r := window_range(m)) is not None and r[1] >= lo and r[0] <= hi}
    static = {cid for cid, m in original.items() if m.is_static}  # type: ignore[attr-defined]
    assert overlapping and overlapping != set(original) - static  # the window leaves something out

    exact = tmp_path / "exact.rrd"
    assert _download(server, run_id, exact, timeline=timeline, start=start, end=end,
                     latest_at="false").status_code == 200
    assert set(_recording_chunks(exact)) == overlapping | static
    assert _run(rerun_bin, "rrd", "verify", str(exact)).returncode == 0

    scene = tmp_path / "scene.rrd"
    _download(server, run_id, scene, timeline=timeline, start=start, end=end)
    got = set(_recording_chunks(scene))
    assert overlapping | static <= got
    for cid in got - overlapping - static:  # latest-at chunks lie before the window
        r = window_range(original[cid])
        assert r is not None and r[1] < lo
    assert got - overlapping - static  # this window starts after data it needs
    assert _run(rerun_bin, "rrd", "verify", str(scene)).returncode == 0


@pytest.mark.parametrize(("params", "name"), [
    ({"timeline": "nope"}, "timeline"), ({"start": "1"}, "timeline"),
    ({"timeline": "frame", "start": "soon"}, "start"), ({"timeline": "sim", "start": "2 weeks"}, "start"),
    ({"timeline": "frame", "start": "5", "end": "1"}, "end"),
])
def test_bad_windows(server: LiveServer, recordings: dict[str, Recording], params: dict[str, str], name: str):
    run_id = recordings["points"].recordings[0]["recording_id"]
    bad = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", params=params, timeout=30)
    assert bad.status_code == 422 and f"'{name}'" in bad.json()["message"], bad.text


def test_exact_trims_rows_to_the_window(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path,
                                        rerun_bin: str):
    from services.rrd.chunk import read_chunk

    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    original = _recording_chunks(rec.path)
    out = tmp_path / "exact.rrd"
    response = _download(server, run_id, out, timeline="frame", start="101", end="104", exact="true",
                         latest_at="false")
    assert response.status_code == 200
    assert _run(rerun_bin, "rrd", "verify", str(out)).returncode == 0
    frames: list[int] = []
    new_ids = 0
    for event in iter_events(out):
        if not isinstance(event, ArrowMessage) or event.store_id.kind != StoreKind.RECORDING:
            continue
        batch = read_chunk(event)
        if "frame" in batch.schema.names:
            values = batch.column("frame").to_pylist()
            assert all(101 <= v <= 104 for v in values), values
            frames += values
        new_ids += event.chunk_id not in original
    assert sorted(set(frames)) == [101, 102, 103, 104]  # every row in the window, none outside
    assert new_ids > 0  # cut chunks are new chunks
    bad = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", params={"exact": "true"}, timeout=30)
    assert bad.status_code == 422 and "'exact'" in bad.json()["message"]


def test_exact_keeps_only_the_latest_row_before_the_window(server: LiveServer, recordings: dict[str, Recording],
                                                           tmp_path: Path):
    from services.rrd.chunk import read_chunk

    run_id = recordings["points"].recordings[0]["recording_id"]
    out = tmp_path / "exact-latest.rrd"
    _download(server, run_id, out, timeline="frame", start="104", end="105", exact="true")
    frames = sorted(v for e in iter_events(out)
                    if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
                    and chunk_meta(e).entity_path == "/world/points"
                    for v in read_chunk(e).column("frame").to_pylist())
    # The window's rows, plus the last row of the chunk wholly before it (its latest-at chunk).
    assert frames == [102, 104, 105]
