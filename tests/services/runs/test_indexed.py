"""Hot downloads planned from the run's chunk index: the same bytes as decoding the run file from its
start (`stream_run`), for every scene and for filters, windows and blueprints; an unfiltered one is
the run file as it is plus End and a footer; and neither an unfiltered nor an entity-filtered one
decompresses a chunk."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import itertools
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from core.errors import UnavailableError
from services.hot.index import INDEX_FILE, HotEntry
from services.hot.read import HotRecording
from services.ingest.service import IngestService
from services.rrd import chunk, iter_events
from services.rrd.chunk_index import CHUNK
from services.rrd.decoder import RrdDecoder
from services.rrd.footer import read_footer
from services.rrd.manifest import is_property_entity
from services.runs import download, indexed, trim
from services.runs.download import EntityFilter, TimeWindow
from services.runs.indexed import stream_hot
from tests.services.ingest import feeding
from tests.services.ingest.factory import ingest_service
from tests.services.rrd.legacy import legacy_file
from tests.services.rrd.recordings import SCENES, Recording
from tests.services.runs.decoded import stream_run

pytestmark = pytest.mark.sdk

# every scene the SDK wrote, the files the rerun CLI re-encoded, and 0.23's chunks without their ids
UPLOADED = (*(s for s in SCENES if s not in ("merge_a", "merge_b")), "merged", "optimized")
LEGACY = "legacy-0.23"

Query = tuple[EntityFilter, bool, TimeWindow | None]  # entities, blueprint, window


def _ingest(root: Path) -> IngestService:
    """An ingest service without a catalog (it plays no part here)."""
    return ingest_service(root, default_robot="r", max_streams=4, close_after=dt.timedelta(minutes=10))


def _upload(service: IngestService, path: Path) -> list[HotRecording]:
    runs = []
    for run_id in feeding.upload(service, iter_events(path)).runs:
        hot = service.hot_recording(run_id)
        assert hot is not None
        index = hot.chunk_index()
        assert index.from_index == len(index.entries) > 0  # served from the index ingest kept, all of it
        runs.append(hot)
    return runs


@pytest.fixture(scope="module")
def hot_runs(
    tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]
) -> Iterator[dict[str, HotRecording]]:
    """`SCENE-i` -> the i-th run of a scene (`merged` has two), and a 0.23 upload (on a node of its
    own: it has the recording id of `blueprint`)."""
    scenes = _ingest(tmp_path_factory.mktemp("scenes"))
    old_sdk = _ingest(tmp_path_factory.mktemp("legacy"))
    try:
        runs = {f"{s}-{i}": hot for s in UPLOADED for i, hot in enumerate(_upload(scenes, recordings[s].path))}
        legacy = legacy_file(
            recordings["blueprint"].path, tmp_path_factory.mktemp("old") / "0.23.rrd", drop_chunk_ids=True
        )
        (runs[LEGACY],) = _upload(old_sdk, legacy)
        yield runs
    finally:
        scenes.hot.close()
        old_sdk.hot.close()


def _window(hot: HotRecording, timeline: str) -> tuple[int, int]:
    """The middle third of the run's span on `timeline`."""
    spans = [(t.min, t.max) for r in hot.chunk_index().rows for t in r.timelines if t.name == timeline]
    lo, hi = min(s[0] for s in spans), max(s[1] for s in spans)
    return lo + (hi - lo) // 3, lo + 2 * (hi - lo) // 3


def _queries(hot: HotRecording) -> list[Query]:
    rows = [r for r in hot.chunk_index().rows if r.kind == CHUNK and r.store_kind == "recording"]
    entities = sorted({r.entity_path or "" for r in rows if not is_property_entity(r.entity_path or "")})
    queries: list[Query] = [(EntityFilter(), True, None), (EntityFilter(), False, None)]
    if entities:
        queries += [
            (EntityFilter([entities[0]]), True, None),
            (EntityFilter(exclude=[entities[-1]]), True, None),
            (EntityFilter(["/**"], ["/__properties/**"]), False, None),
        ]
    for timeline in sorted(hot.timeline_types):
        start, end = _window(hot, timeline)
        queries += [
            (EntityFilter(), True, TimeWindow(timeline, start, end)),
            (EntityFilter(), True, TimeWindow(timeline, start, end, latest_at=False)),
            (EntityFilter(), False, TimeWindow(timeline, start, None)),
            (EntityFilter(), True, TimeWindow(timeline, None, start)),
            (EntityFilter(), True, TimeWindow(timeline, start, end, exact=True)),
            (EntityFilter(), True, TimeWindow(timeline, start, end, latest_at=False, exact=True)),
        ]
        if entities:
            queries.append((EntityFilter([entities[0]]), True, TimeWindow(timeline, start, end, exact=True)))
    return queries


def _old(hot: HotRecording, query: Query) -> bytes:
    """The download as decoding the run file from its start gives it."""
    entities, blueprint, window = query
    with _numbered_cuts():
        return b"".join(stream_run(hot.path, hot.size, entities, blueprint=blueprint, window=window))


def _new(hot: HotRecording, query: Query) -> bytes:
    entities, blueprint, window = query
    with _numbered_cuts():
        return b"".join(stream_hot(hot, entities, blueprint=blueprint, window=window))


@contextlib.contextmanager
def _numbered_cuts() -> Iterator[None]:
    """Chunks cut by an exact window get ids 1, 2, ... (not random ones): two downloads compare byte for byte."""
    numbers = itertools.count(1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(trim, "new_chunk_id", lambda: next(numbers).to_bytes(16, "big"))
        yield


def _verify(rerun_bin: str, data: bytes, path: Path) -> None:
    path.write_bytes(data)
    verify = subprocess.run([rerun_bin, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stdout + verify.stderr


@pytest.mark.parametrize("name", [f"{s}-0" for s in UPLOADED] + ["merged-1", LEGACY])
def test_a_hot_download_is_what_decoding_the_run_file_gives(hot_runs: dict[str, HotRecording], name: str):
    hot = hot_runs[name]
    queries = _queries(hot)
    assert len(queries) > 2 or name.startswith("static")
    for query in queries:
        old, new = _old(hot, query), _new(hot, query)
        assert new == old, (name, query, len(new), len(old))


@pytest.mark.parametrize("name", ["points-0", "large-0", "blueprint-0", LEGACY])
def test_an_unfiltered_hot_download_is_the_run_file_then_a_footer(
    hot_runs: dict[str, HotRecording], name: str, rerun_bin: str, tmp_path: Path
):
    hot = hot_runs[name]
    data = _new(hot, (EntityFilter(), True, None))
    _verify(rerun_bin, data, tmp_path / "run.rrd")
    with open(tmp_path / "run.rrd", "rb") as fh:
        footer = read_footer(fh)
    assert footer is not None and footer.manifests
    stored = hot.path.read_bytes()[: hot.size]
    if name == LEGACY:  # 0.23 sent chunks without their ids: each gets them appended, so the stream grows
        assert len(data) > hot.size + 17 * sum(r.kind == CHUNK for r in hot.chunk_index().rows)
    else:
        assert data[: hot.size] == stored  # copied as it is


@pytest.mark.parametrize("name", ["points-0", "large-0", "blueprint-0", "merged-1", LEGACY])
@pytest.mark.interpreted("services.rrd.chunk")
def test_unfiltered_and_entity_filtered_hot_downloads_decompress_no_chunk(
    hot_runs: dict[str, HotRecording], name: str, monkeypatch: pytest.MonkeyPatch
):
    """Everything a download needs (what to keep, where it lies, the footer's manifest) comes from the
    chunk index: reading a chunk's payload fails the test."""
    hot = hot_runs[name]
    entity = sorted(
        {r.entity_path or "" for r in hot.chunk_index().rows if r.kind == CHUNK and r.store_kind == "recording"}
    )[-1]
    timeline = sorted(hot.timeline_types)[0]
    start, end = _window(hot, timeline)
    queries: list[Query] = [
        (EntityFilter(), True, None),
        (EntityFilter(), False, None),
        (EntityFilter([entity]), True, None),
        (EntityFilter(exclude=[entity]), True, None),
        (EntityFilter(), True, TimeWindow(timeline, start, end)),  # whole chunks: planned from the index too
    ]
    expected = [_old(hot, q) for q in queries]

    def no_decompression(msg: object) -> bytes:
        raise AssertionError("a chunk's payload was decompressed")

    monkeypatch.setattr(chunk, "decompress_payload", no_decompression)
    with pytest.raises(AssertionError, match="decompressed"):
        _old(hot, queries[0])  # the old path reads every chunk's payload
    assert [_new(hot, q) for q in queries] == expected


def test_an_unfiltered_hot_download_starts_before_the_index_is_read_through(
    hot_runs: dict[str, HotRecording], monkeypatch: pytest.MonkeyPatch
):
    """Rows are chosen as the index is parsed: a run of many small chunks sends its first bytes
    after the first of them, not after all (here with pieces and reads made small)."""
    hot = hot_runs["points-0"]
    total = len(hot.chunk_index().entries)
    monkeypatch.setattr(download, "FLUSH_BYTES", 1024)
    monkeypatch.setattr(indexed, "FIRST_READ_BYTES", 2048)
    parsed = 0
    entries = HotRecording.index_entries

    def counted(self: HotRecording) -> Iterator[HotEntry]:
        nonlocal parsed
        for entry in entries(self):
            parsed += 1
            yield entry

    monkeypatch.setattr(HotRecording, "index_entries", counted)
    stream = stream_hot(hot, EntityFilter())
    first = next(stream)
    assert len(first) >= 1024 and 0 < parsed < total / 2, (parsed, total)
    rest = b"".join(stream)
    assert parsed == total and bytes(first) + rest == _old(hot, (EntityFilter(), True, None))


def test_the_first_piece_goes_out_with_the_first_chunk(hot_runs: dict[str, HotRecording]):
    """A download well under FLUSH_BYTES (a window of a small entity, most often) does not wait for
    its last chunk to send its first: the first piece holds the stream's start and one chunk."""
    hot = hot_runs["points-0"]
    expected = _old(hot, (EntityFilter(), True, None))
    assert len(expected) < download.FLUSH_BYTES
    stream = stream_hot(hot, EntityFilter())
    first = bytes(next(stream))
    rest = b"".join(stream)
    assert rest and first + rest == expected
    kinds = [type(e).__name__ for e in iter_events_of(first)]
    assert kinds.count("ArrowMessage") == 1 and kinds[-1] == "ArrowMessage", kinds


def iter_events_of(data: bytes) -> list[object]:
    """The events whole in `data` (the start of a stream)."""
    decoder = RrdDecoder()
    return list(decoder.feed(data))


def test_a_run_sealed_while_it_is_read_is_not_served_short(
    hot_runs: dict[str, HotRecording], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """Promotion removes a sealed run's hot files: a download that had only opened the run file
    then has no index and no file to read it from, and fails rather than end the stream early."""
    hot = hot_runs["points-0"]
    for name in (hot.path.name, INDEX_FILE):
        shutil.copyfile(hot.path.with_name(name), tmp_path / name)
    copy = dataclasses.replace(hot, path=tmp_path / hot.path.name)
    entries = HotRecording.index_entries

    def sealed_meanwhile(self: HotRecording) -> Iterator[HotEntry]:
        (tmp_path / INDEX_FILE).unlink()
        self.path.unlink()
        return entries(self)

    monkeypatch.setattr(HotRecording, "index_entries", sealed_meanwhile)
    with pytest.raises(UnavailableError, match="sealed while it was being read"):
        b"".join(stream_hot(copy, EntityFilter()))
