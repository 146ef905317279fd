"""summarize / format_time and `fleet rrd inspect` on real recordings."""

from __future__ import annotations

import calendar
import datetime as dt
import io
import json
import shutil
import struct
import subprocess
import sys
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.rrd import ArrowMessage, StoreKind, errors, iter_events
from services.rrd.footer import summarize_from_footer
from services.rrd.summary import RrdSummary, StoreSummary, format_time, summarize
from tests.services.rrd.recordings import CLI_FILES, Recording, walk_frames

sdk = pytest.mark.sdk


def _fleet_bin() -> str:
    candidate = Path(sys.executable).parent / "fleet"
    return str(candidate) if candidate.exists() else (shutil.which("fleet") or "fleet")


FLEET = _fleet_bin()


def recording_store(summary: RrdSummary, recording_id: str) -> StoreSummary:
    (store,) = [
        s
        for s in summary.stores.values()
        if s.store_id.kind == StoreKind.RECORDING and s.store_id.recording_id == recording_id
    ]
    return store


def check_store_against_truth(store: StoreSummary, truth: dict[str, Any]) -> None:
    entities = truth["entities"]
    assert store.store_id.application_id == truth["application_id"]
    assert set(store.entities) == set(entities)
    assert store.rows == sum(e["static_rows"] + e["temporal_rows"] for e in entities.values())
    assert store.chunks == sum(e.chunks for e in store.entities.values())
    assert store.bytes == sum(e.bytes for e in store.entities.values())
    for path, want in entities.items():
        got = store.entities[path]
        assert got.rows == want["static_rows"] + want["temporal_rows"], path
        assert got.archetypes == set(want["archetypes"]), path
        assert got.components == set(want["components"]), path
        if want["temporal_rows"] == 0:
            assert got.static_chunks == got.chunks, path
        elif want["static_rows"] == 0:
            assert got.static_chunks == 0, path
        else:
            assert 0 < got.static_chunks < got.chunks, path

    expected: dict[str, dict[str, Any]] = {}
    for want in entities.values():
        for name, tl in want["timelines"].items():
            known = expected.setdefault(name, dict(tl))
            known["min"], known["max"] = min(known["min"], tl["min"]), max(known["max"], tl["max"])
    has_temporal = any(e["temporal_rows"] for e in entities.values())
    assert set(store.timelines) == set(expected) | ({"log_time"} if has_temporal else set())
    for name, want in expected.items():
        got_tl = store.timelines[name]
        assert (got_tl.type, got_tl.min, got_tl.max) == (want["type"], want["min"], want["max"]), name
    if has_temporal:
        lo, hi = truth["log_time"]
        log_time = store.timelines["log_time"]
        assert log_time.type == "timestamp"
        assert lo <= log_time.min <= log_time.max <= hi


# --- summarize -------------------------------------------------------------------------------


@sdk
def test_summary_matches_truth(whole: Recording):
    summary = summarize(iter_events(whole.path), str(whole.path))
    assert summary.error is None
    assert summary.streams == 1
    assert summary.rerun_versions == ["0.41.0"]
    assert summary.footers == (1 if whole.truth["footer"] else 0)

    events = list(iter_events(whole.path))
    chunks = [e for e in events if isinstance(e, ArrowMessage)]
    assert sum(s.chunks for s in summary.stores.values()) == len(chunks)
    assert sum(s.bytes for s in summary.stores.values()) == sum(len(c.raw) for c in chunks)
    for store in summary.stores.values():
        assert store.sdk_version == "0.41.0"
        assert store.source is not None and store.source.startswith("python_sdk")
        assert store.store_infos == (1 if whole.name in CLI_FILES else 2)
        assert store.chunks == sum(c.store_id == store.store_id for c in chunks)

    for truth in whole.recordings:
        store = recording_store(summary, truth["recording_id"])
        check_store_against_truth(store, truth)
        assert store.blueprint_activations == 0
    blueprints = [s for s in summary.stores.values() if s.store_id.kind == StoreKind.BLUEPRINT]
    assert len(blueprints) == sum(r["blueprint"] for r in whole.recordings)
    for blueprint in blueprints:
        assert blueprint.blueprint_activations == 1
        assert blueprint.chunks > 0
        assert set(blueprint.timelines) == {"blueprint", "log_time"}


@sdk
def test_summary_to_dict(recordings: dict[str, Recording]):
    rec = recordings["blueprint"]
    summary = summarize(iter_events(rec.path), "bp.rrd")
    summary.bytes_read = len(rec.data)
    doc = json.loads(json.dumps(summary.to_dict()))
    assert doc["source"] == "bp.rrd" and doc["bytes"] == len(rec.data)
    assert (doc["streams"], doc["footers"], doc["error"]) == (1, 1, None)
    by_kind = {s["kind"]: s for s in doc["stores"]}
    assert set(by_kind) == {"recording", "blueprint"}
    recording = by_kind["recording"]
    assert (recording["application_id"], recording["recording_id"]) == ("fleet_bp", "rec-blueprint")
    assert by_kind["blueprint"]["blueprint_activations"] == 1
    truth = rec.recordings[0]["entities"]
    assert [e["path"] for e in recording["entities"]] == sorted(truth)
    for entity in recording["entities"]:
        assert entity["rows"] == truth[entity["path"]]["static_rows"] + truth[entity["path"]]["temporal_rows"]
        assert entity["archetypes"] == sorted(truth[entity["path"]]["archetypes"])
    frame = next(t for t in recording["timelines"] if t["name"] == "frame")
    assert (frame["type"], frame["min"], frame["max"], frame["min_text"], frame["max_text"]) == (
        "sequence",
        0,
        2,
        "0",
        "2",
    )
    log_time = next(t for t in recording["timelines"] if t["name"] == "log_time")
    assert log_time["min_text"] == format_time("timestamp", log_time["min"])


@sdk
def test_summary_of_cut_file(recordings: dict[str, Recording]):
    rec = recordings["cut"]
    summary = summarize(iter_events(rec.path), "cut.rrd")
    assert isinstance(summary.error, errors.TruncatedError)
    assert summary.error.offset == rec.truth["cut_message_offset"]
    assert summary.footers == 0
    store = recording_store(summary, "rec-points")
    frames, _ = walk_frames(recordings["points"].data)
    before = [f for f in frames if f.kind == 2 and f.offset < rec.truth["cut_message_offset"]]
    assert store.chunks == len(before) > 0
    assert store.bytes == sum(f.length for f in before)


@sdk
def test_summary_of_concatenated_streams(recordings: dict[str, Recording]):
    data = recordings["no_footer"].data + recordings["points"].data + recordings["merged"].data
    summary = summarize(iter_events(io.BytesIO(data)), "cat")
    assert summary.error is None
    assert summary.streams == 3
    assert summary.rerun_versions == ["0.41.0"] * 3
    assert summary.footers == 2
    assert {s.store_id.recording_id for s in summary.stores.values()} == {
        "rec-no-footer",
        "rec-points",
        "rec-merge-a",
        "rec-merge-b",
    }
    check_store_against_truth(recording_store(summary, "rec-points"), recordings["points"].recordings[0])


@sdk
def test_summary_counts_what_precedes_a_bad_message(recordings: dict[str, Recording]):
    data = bytearray(recordings["scalars"].data)
    frames, _ = walk_frames(bytes(data))
    struct.pack_into("<Q", data, frames[4].offset, 7)  # an unknown message kind
    summary = summarize(iter_events(io.BytesIO(bytes(data))), "bad")
    assert isinstance(summary.error, errors.UnknownMessageKindError)
    assert summary.error.offset == frames[4].offset
    assert summary.streams == 1
    assert recording_store(summary, "rec-scalars").chunks == sum(f.kind == 2 for f in frames[:4])


# --- format_time ------------------------------------------------------------------------------


def test_format_time_examples():
    assert format_time("timestamp", 1_700_000_000_123_456_789) == "2023-11-14T22:13:20.123456789Z"
    assert format_time("timestamp", 0) == "1970-01-01T00:00:00.000000000Z"
    assert format_time("timestamp", -1) == "1969-12-31T23:59:59.999999999Z"
    assert format_time("duration", 1_500_000_000) == "1.5s"
    assert format_time("duration", 0) == "0s"
    assert format_time("duration", 123) == "0.000000123s"
    assert format_time("duration", -2_000_000_000) == "-2s"
    assert format_time("duration", 60 * 10**9) == "60s"
    assert format_time("sequence", 42) == "42"
    assert format_time("sequence", -7) == "-7"


def _parse_timestamp(text: str) -> int:
    assert text.endswith("Z")
    whole, _, nanos = text[:-1].partition(".")
    assert len(nanos) == 9
    seconds = calendar.timegm(dt.datetime.strptime(whole, "%Y-%m-%dT%H:%M:%S").timetuple())
    return seconds * 1_000_000_000 + int(nanos)


@given(st.integers(-(2**63), 2**63 - 1))
def test_format_timestamp_is_exact(value: int):
    assert _parse_timestamp(format_time("timestamp", value)) == value


@given(st.integers(-(10**15), 10**15))  # up to ~11.6 days
def test_format_duration_is_exact(value: int):
    text = format_time("duration", value)
    assert text.endswith("s")
    assert Decimal(text[:-1]) * 1_000_000_000 == value


def test_format_long_duration_is_exact():
    assert format_time("duration", 123_456_789_123_456_789) == "123456789.123456789s"


@given(st.integers(-(2**63), 2**63 - 1))
def test_format_sequence(value: int):
    assert format_time("sequence", value) == str(value)


# --- fleet rrd inspect ------------------------------------------------------------------------


def fleet(*args: str | Path, stdin: bytes | None = None) -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([FLEET, *map(str, args)], input=stdin, capture_output=True, timeout=120)


def check_inspect_doc(doc: dict[str, Any], rec: Recording) -> None:
    assert doc["error"] is None
    assert doc["streams"] == 1 and doc["rerun_versions"] == ["0.41.0"]
    assert doc["bytes"] == len(rec.data)
    (truth,) = rec.recordings
    (store,) = [s for s in doc["stores"] if s["kind"] == "recording"]
    assert (store["application_id"], store["recording_id"]) == (truth["application_id"], truth["recording_id"])
    assert store["sdk_version"] == "0.41.0"
    assert {e["path"]: e["rows"] for e in store["entities"]} == {
        path: e["static_rows"] + e["temporal_rows"] for path, e in truth["entities"].items()
    }
    assert store["rows"] == sum(e["rows"] for e in store["entities"])
    chunks = [e for e in iter_events(rec.path) if isinstance(e, ArrowMessage)]
    assert store["chunks"] == sum(e["chunks"] for e in store["entities"]) == len(chunks)


@sdk
def test_inspect_json(recordings: dict[str, Recording]):
    rec = recordings["scalars"]
    result = fleet("rrd", "inspect", "--json", rec.path)
    assert result.returncode == 0, result.stderr
    (doc,) = json.loads(result.stdout)
    assert doc["source"] == str(rec.path)
    assert doc["footers"] == 1
    check_inspect_doc(doc, rec)


@sdk
def test_inspect_json_several_files(recordings: dict[str, Recording]):
    names = ["static", "properties", "no_footer"]
    result = fleet("rrd", "inspect", "--json", *(recordings[n].path for n in names))
    assert result.returncode == 0, result.stderr
    docs = json.loads(result.stdout)
    assert [d["source"] for d in docs] == [str(recordings[n].path) for n in names]
    for doc, name in zip(docs, names, strict=True):
        check_inspect_doc(doc, recordings[name])
    assert [d["footers"] for d in docs] == [1, 1, 0]


@sdk
def test_inspect_cut_file(recordings: dict[str, Recording]):
    rec = recordings["cut"]
    offset = rec.truth["cut_message_offset"]
    result = fleet("rrd", "inspect", "--json", rec.path)
    assert result.returncode == 1
    errors_lines = [line for line in result.stderr.decode().splitlines() if "truncated" in line]
    assert len(errors_lines) == 1
    assert f"byte {offset}" in errors_lines[0] and str(rec.path) in errors_lines[0]
    (doc,) = json.loads(result.stdout)
    assert doc["error"]["type"] == "TruncatedError"
    assert doc["error"]["offset"] == offset
    assert doc["bytes"] == len(rec.data)
    (store,) = doc["stores"]
    assert (store["recording_id"], store["sdk_version"]) == ("rec-points", "0.41.0")
    events = [e for e in iter_events(recordings["points"].path) if e.offset < offset]
    assert store["chunks"] == sum(isinstance(e, ArrowMessage) for e in events) > 0


@sdk
@pytest.mark.parametrize("args", [(), ("-",)], ids=["no-args", "dash"])
def test_inspect_stdin(recordings: dict[str, Recording], args: tuple[str, ...]):
    rec = recordings["transforms"]
    from_file = fleet("rrd", "inspect", "--json", rec.path)
    from_stdin = fleet("rrd", "inspect", "--json", *args, stdin=rec.data)
    assert from_stdin.returncode == 0, from_stdin.stderr
    (doc,) = json.loads(from_stdin.stdout)
    assert doc["source"] == "<stdin>"
    check_inspect_doc(doc, rec)
    (file_doc,) = json.loads(from_file.stdout)
    assert (doc["index"], file_doc["index"]) == ("scan", "footer")  # stdin cannot seek to the footer
    assert {**doc, "source": None, "index": None} == {**file_doc, "source": None, "index": None}


@sdk
def test_footer_summary_equals_full_scan(footer_file: Recording):
    from_footer = summarize_from_footer(str(footer_file.path))
    assert from_footer is not None and from_footer.index == "footer"
    scanned = summarize(iter_events(footer_file.path), str(footer_file.path))
    assert {**from_footer.to_dict(), "bytes": 0, "index": None} == {**scanned.to_dict(), "index": None}


@sdk
def test_footer_summary_refuses_what_it_cannot_trust(recordings: dict[str, Recording], tmp_path: Path):
    assert summarize_from_footer(str(recordings["no_footer"].path)) is None
    concatenated = tmp_path / "cat.rrd"
    concatenated.write_bytes(recordings["merge_a"].data + recordings["merge_b"].data)
    assert summarize_from_footer(str(concatenated)) is None  # offsets are relative to the last stream
    damaged = bytearray(recordings["points"].data)
    damaged[-40] ^= 0xFF  # inside the footer payload: the CRC no longer matches
    (tmp_path / "damaged.rrd").write_bytes(damaged)
    assert summarize_from_footer(str(tmp_path / "damaged.rrd")) is None
    assert fleet("rrd", "inspect", "--json", "--scan", recordings["points"].path).returncode == 0


@sdk
def test_inspect_text(recordings: dict[str, Recording]):
    rec = recordings["blueprint"]
    result = fleet("rrd", "inspect", rec.path)
    assert result.returncode == 0, result.stderr
    out = result.stdout.decode()
    assert "rec-blueprint" in out and "fleet_bp" in out and "0.41.0" in out
    for path in rec.recordings[0]["entities"]:
        assert path in out
