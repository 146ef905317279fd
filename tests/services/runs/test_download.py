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
from tests.services.runs import decoded

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
    response = httpx.get(
        f"{server.url}/v1/runs/{run_id}/recording.rrd",
        params=params,  # type: ignore[arg-type]
        headers={"Origin": "http://localhost:9090"},
        timeout=120,
    )  # as a browser viewer asks
    out.write_bytes(response.content)
    return response


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(args), capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("name", NAMES)
def test_full_download_equals_the_original(
    server: LiveServer, recordings: dict[str, Recording], name: str, rerun_bin: str, tmp_path: Path
):
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


def test_entity_filter_equals_rerun_rrd_filter(
    server: LiveServer, recordings: dict[str, Recording], rerun_bin: str, tmp_path: Path
):
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
    got = {
        chunk_meta(e).entity_path
        for e in iter_events(out)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    }
    properties = {p for p in all_paths if p == "/__properties" or p.startswith("/__properties/")}
    assert properties  # the SDK logs the recording's start time there
    # the recording's properties stay with an entity filter (an include need not name them)
    assert got == {p for p in all_paths if p == "/world" or p.startswith("/world/")} | properties and got
    excluded = sorted(got)[0]
    _download(server, run_id, out, include="/world/**", exclude=excluded)
    assert excluded not in {chunk_meta(e).entity_path for e in iter_events(out) if isinstance(e, ArrowMessage)}


def test_blueprint_can_be_left_out(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path):
    run_id = recordings["blueprint"].recordings[0]["recording_id"]
    out = tmp_path / "nobp.rrd"
    _download(server, run_id, out, blueprint="false")
    kinds = {e.store_id.kind for e in iter_events(out) if isinstance(e, ArrowMessage)}
    assert kinds == {StoreKind.RECORDING}


def test_the_viewer_loader_saves_the_same(
    server: LiveServer, recordings: dict[str, Recording], rerun_bin: str, tmp_path: Path
):
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
    return {
        e.chunk_id: chunk_meta(e)  # type: ignore[misc]
        for e in iter_events(path)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    }


@pytest.mark.parametrize(
    ("timeline", "start", "end", "lo", "hi"),
    [
        ("frame", "104", "105", 104, 105),
        ("sim", "0.75s", "1s", 750_000_000, 1_000_000_000),
    ],
)
def test_time_window(
    server: LiveServer,
    recordings: dict[str, Recording],
    tmp_path: Path,
    rerun_bin: str,
    timeline: str,
    start: str,
    end: str,
    lo: int,
    hi: int,
):
    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    original = _recording_chunks(rec.path)

    def window_range(meta: object) -> tuple[int, int] | None:
        tl = next((t for t in meta.timelines if t.name == timeline), None)  # type: ignore[attr-defined]
        return None if tl is None else (tl.range.min, tl.range.max)

    overlapping = {
        cid for cid, m in original.items() if (r := window_range(m)) is not None and r[1] >= lo and r[0] <= hi
    }
    static = {cid for cid, m in original.items() if m.is_static}  # type: ignore[attr-defined]
    assert overlapping and overlapping != set(original) - static  # the window leaves something out

    exact = tmp_path / "exact.rrd"
    assert (
        _download(server, run_id, exact, timeline=timeline, start=start, end=end, latest_at="false").status_code == 200
    )
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


@pytest.mark.parametrize(
    ("params", "name"),
    [
        ({"timeline": "nope"}, "timeline"),
        ({"start": "1"}, "timeline"),
        ({"timeline": "frame", "start": "soon"}, "start"),
        ({"timeline": "sim", "start": "2 weeks"}, "start"),
        ({"timeline": "frame", "start": "5", "end": "1"}, "end"),
    ],
)
def test_bad_windows(server: LiveServer, recordings: dict[str, Recording], params: dict[str, str], name: str):
    run_id = recordings["points"].recordings[0]["recording_id"]
    bad = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", params=params, timeout=30)
    assert bad.status_code == 422 and f"'{name}'" in bad.json()["message"], bad.text


def test_exact_trims_rows_to_the_window(
    server: LiveServer, recordings: dict[str, Recording], tmp_path: Path, rerun_bin: str
):
    from services.rrd.chunk import read_chunk

    rec = recordings["points"]
    run_id = rec.recordings[0]["recording_id"]
    original = _recording_chunks(rec.path)
    out = tmp_path / "exact.rrd"
    response = _download(server, run_id, out, timeline="frame", start="101", end="104", exact="true", latest_at="false")
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


def test_exact_keeps_only_the_latest_row_before_the_window(
    server: LiveServer, recordings: dict[str, Recording], tmp_path: Path
):
    from services.rrd.chunk import read_chunk

    run_id = recordings["points"].recordings[0]["recording_id"]
    out = tmp_path / "exact-latest.rrd"
    _download(server, run_id, out, timeline="frame", start="104", end="105", exact="true")
    frames = sorted(
        v
        for e in iter_events(out)
        if isinstance(e, ArrowMessage)
        and e.store_id.kind == StoreKind.RECORDING
        and chunk_meta(e).entity_path == "/world/points"
        for v in read_chunk(e).column("frame").to_pylist()
    )
    # The window's rows, plus the newest row before it: frame 103, in the chunk (103-105) that straddles
    # the start, not the last row of the chunk wholly before it (102: its colors are older than 103's,
    # which the viewer shows at 104, a row without colors).
    assert frames == [103, 104, 105]


def _entities(path: Path) -> set[str]:
    return {
        chunk_meta(e).entity_path
        for e in iter_events(path)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    }


def test_entity_filters_keep_the_recordings_properties_unless_excluded(
    server: LiveServer, recordings: dict[str, Recording], tmp_path: Path
):
    run_id = recordings["points"].recordings[0]["recording_id"]
    out = tmp_path / "props.rrd"
    kept: list[dict[str, object]] = [
        {"include": "/world/**"},
        {"include": "/world/points"},
        {"exclude": "/world/**"},
        {"exclude": "/**"},
        {"include": "/world/**", "exclude": "/world/points"},
    ]
    for params in kept:
        assert _download(server, run_id, out, **params).status_code == 200
        assert "/__properties" in _entities(out), params
    dropped: list[dict[str, object]] = [
        {"exclude": "/__properties"},
        {"exclude": "/__properties/**"},
        {"include": ["/world/**", "/__properties/**"], "exclude": "/__properties/**"},
    ]
    for params in dropped:
        assert _download(server, run_id, out, **params).status_code == 200
        assert "/__properties" not in _entities(out) and _entities(out), params


def test_entity_patterns_are_bounded(server: LiveServer, recordings: dict[str, Recording]):
    from services.rrd.entity_patterns import MAX_PATTERN_LENGTH, MAX_PATTERNS

    run_id = recordings["points"].recordings[0]["recording_id"]
    url = f"{server.url}/v1/runs/{run_id}/recording.rrd"
    for params, name in (
        ({"exclude": [f"/x{i}" for i in range(MAX_PATTERNS + 1)]}, "exclude"),
        ({"include": [f"/x{i}" for i in range(MAX_PATTERNS + 1)]}, "include"),
        ({"exclude": "/" + "a" * MAX_PATTERN_LENGTH}, "exclude"),
    ):
        bad = httpx.get(url, params=params, timeout=30)
        assert bad.status_code == 422 and f"'{name}'" in bad.json()["message"], bad.text
    assert httpx.get(url, params={"exclude": [f"/x{i}" for i in range(MAX_PATTERNS)]}, timeout=60).status_code == 200


def test_pattern_matching_cost_is_per_entity_not_per_chunk(
    recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    """Each entity path is matched against the patterns once, however many chunks it has."""
    from services.runs import download

    path = recordings["points"].path
    chunks = [chunk_meta(e).entity_path for e in iter_events(path) if isinstance(e, ArrowMessage)]
    assert len(chunks) > 2 * len(set(chunks))  # many chunks per entity
    calls = 0
    matches = download._matches

    def counting(pattern: str, entity: str) -> bool:
        nonlocal calls
        calls += 1
        return matches(pattern, entity)

    monkeypatch.setattr(download, "_matches", counting)
    patterns = [f"/nowhere/{i}/**" for i in range(200)]
    data = b"".join(decoded.stream_run(path, path.stat().st_size, download.EntityFilter(exclude=patterns)))
    assert len(data) > 0.9 * path.stat().st_size  # nothing was excluded
    assert calls <= len(set(chunks)) * len(patterns), (calls, len(chunks))


@pytest.mark.parametrize(
    ("timeline", "start", "end"),
    [
        ("frame", "-99999999999999999999", "5"),
        ("frame", "0", "9223372036854775808"),
        ("log_time", "2263-01-01T00:00:00Z", None),
        ("log_time", "1600-01-01", "2026-01-01"),
        ("sim", "9999999999h", None),
    ],
)
def test_windows_outside_int64_are_refused_up_front(
    server: LiveServer, recordings: dict[str, Recording], timeline: str, start: str, end: str | None
):
    run_id = recordings["points"].recordings[0]["recording_id"]
    params = {"timeline": timeline, "start": start, "exact": "true", **({"end": end} if end else {})}
    bad = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", params=params, timeout=30)
    name = "end" if end and end.startswith("9223") else "start"
    assert bad.status_code == 422 and f"'{name}'" in bad.json()["message"], bad.text
    assert "outside the range" in bad.json()["message"]
