"""Ingest of real SDK recordings: runs filed in the hot tier, each chunk once, the catalog in step."""

from __future__ import annotations

import asyncio
import datetime as dt
import io
import json
import os
import subprocess
from typing import Any

import pytest

from catalog import queries
from catalog.db import session_scope
from core.errors import FleetError, InsufficientStorageError, InvalidArgumentError, ResourceExhaustedError
from core.ids import UnsafeIdError
from services.ingest.service import IngestReport, IngestService
from services.rrd import ArrowMessage, StoreKind, errors, iter_events
from services.rrd.chunk import chunk_meta, read_chunk
from services.rrd.messages import BlueprintActivationMessage, StoreInfoMessage
from services.settings import Durability
from tests.services.ingest import feeding
from tests.services.ingest.conftest import Factory
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk


def upload(service: IngestService, data_or_path: object) -> IngestReport:
    return feeding.upload(service, iter_events(data_or_path))  # type: ignore[arg-type]


def chunk_ids(path: object) -> list[bytes]:
    return [e.chunk_id for e in iter_events(path) if isinstance(e, ArrowMessage)]  # type: ignore[arg-type, misc]


def catalog_run(service: IngestService, run_id: str) -> dict[str, Any]:
    assert service.catalog is not None
    with session_scope(service.catalog) as session:
        run = queries.get_run(session, run_id)
        assert run is not None
        return {
            **{
                c: getattr(run, c)
                for c in ("robot_id", "application_id", "status", "tier", "chunks", "rows", "bytes", "sdk_version")
            },
            "properties": json.loads(run.properties),
            "date": run.date,
            "entities": {e.path: (e.chunks, e.rows) for e in queries.run_entities(session, run_id)},
            "timelines": {t.name: (t.type, t.min, t.max) for t in queries.run_timelines(session, run_id)},
        }


def test_upload_files_a_run_and_catalogs_it(make_service: Factory, recordings: dict[str, Recording], rerun_bin: str):
    service = make_service()
    rec = recordings["properties"]
    report = upload(service, rec.path)
    run_id = rec.recordings[0]["recording_id"]
    original = chunk_ids(rec.path)
    assert report.runs == [run_id] and report.chunks_new == len(original) and report.chunks_duplicate == 0
    hot_file = service.runs[run_id].hot.path
    assert sorted(chunk_ids(hot_file)) == sorted(original)
    subprocess.run(
        [rerun_bin, "rrd", "verify", "--check-footers", "false", str(hot_file)], check=True, capture_output=True
    )
    row = catalog_run(service, run_id)
    truth = rec.recordings[0]
    assert (row["application_id"], row["status"], row["tier"], row["sdk_version"]) == (
        truth["application_id"],
        "closed",
        "hot",
        "0.41.0",
    )
    assert row["chunks"] == len(original)
    assert set(row["entities"]) == set(truth["entities"])
    assert row["bytes"] == hot_file.stat().st_size


def test_second_upload_is_all_duplicates(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    rec = recordings["points"]
    first = upload(service, rec.path)
    size = service.runs[first.runs[0]].hot.size
    second = upload(service, rec.path)
    assert (second.chunks_new, second.chunks_duplicate, second.bytes_new) == (0, first.chunks_new, 0)
    assert service.runs[first.runs[0]].hot.size == size  # nothing written again


def test_robot_from_property_and_token_never_stored(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    rec = recordings["properties"]
    run_id = upload(service, rec.path).runs[0]
    props = rec.recordings[0]["properties"]
    row = catalog_run(service, run_id)
    if "fleet" in props and "robot_id" in props["fleet"]:
        assert row["robot_id"] == props["fleet"]["robot_id"]
    stored = [read_chunk(e) for e in iter_events(service.runs[run_id].hot.path) if isinstance(e, ArrowMessage)]
    for batch in stored:
        assert "token" not in batch.schema.names
    assert "token" not in json.dumps(row["properties"])


def test_cut_upload_keeps_what_precedes_the_fault(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    cut = recordings["cut"]
    source = service.open_source(live=False)
    with pytest.raises(errors.TruncatedError):
        feeding.feed(service, source, iter_events(cut.path))
    report = asyncio.run(service.finish_upload(source))
    before = chunk_ids_before_error(cut.path)
    assert report.chunks_new == len(before) > 0
    assert sorted(chunk_ids(service.runs[report.runs[0]].hot.path)) == sorted(before)


def chunk_ids_before_error(path: object) -> list[bytes]:
    ids = []
    try:
        for event in iter_events(path):  # type: ignore[arg-type]
            if isinstance(event, ArrowMessage):
                ids.append(event.chunk_id)
    except errors.RrdError:
        pass
    return ids  # type: ignore[return-value]


def test_blueprint_is_kept_with_its_run(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    rec = recordings["blueprint"]
    report = upload(service, rec.path)
    assert report.runs == [rec.recordings[0]["recording_id"]]  # one run: the blueprint is not a run
    events = list(iter_events(service.runs[report.runs[0]].hot.path))
    kinds = {e.store_id.kind for e in events if isinstance(e, StoreInfoMessage)}
    assert kinds == {StoreKind.RECORDING, StoreKind.BLUEPRINT}
    assert any(isinstance(e, BlueprintActivationMessage) for e in events)
    assert sorted(chunk_ids(service.runs[report.runs[0]].hot.path)) == sorted(chunk_ids(rec.path))


def test_unsafe_recording_id_is_refused(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    data = recordings["points"].data.replace(b"rec-points", b"rec/points")
    with pytest.raises(UnsafeIdError, match="cannot be used in object keys"):
        upload(service, io.BytesIO(data))
    assert service.runs == {}
    assert not any(service.hot.root.iterdir())


def test_message_before_store_info_is_refused(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    source = service.open_source(live=False)
    arrow = next(e for e in iter_events(recordings["points"].path) if isinstance(e, ArrowMessage))
    with pytest.raises(InvalidArgumentError, match="before its SetStoreInfo"):
        service.accept(source, arrow)


def test_restart_recovers_runs_and_trims_a_torn_tail(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    rec = recordings["scalars"]
    run_id = upload(service, rec.path).runs[0]
    path = service.runs[run_id].hot.path
    whole = path.stat().st_size
    service.hot.close()
    with open(path, "ab") as fh:  # a crash in the middle of writing a message
        fh.write((2).to_bytes(8, "little") + (5000).to_bytes(8, "little") + b"partial")
    restarted = make_service()
    assert restarted.recover() == [run_id]
    assert path.stat().st_size == whole
    assert restarted.runs[run_id].chunk_ids == set(chunk_ids(rec.path))
    assert upload(restarted, rec.path).chunks_new == 0  # exactly once across the restart
    row = catalog_run(restarted, run_id)
    assert row["chunks"] == len(chunk_ids(rec.path)) and row["status"] == "closed"


def test_durability_always_syncs_before_answering(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service(durability=Durability.ALWAYS)
    report = upload(service, recordings["points"].path)
    assert service.runs[report.runs[0]].hot.dirty is False


@pytest.mark.parametrize("live", [False, True])
def test_durability_always_fsyncs_off_the_event_loop(
    make_service: Factory, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch, live: bool
):
    """An upload (`finish_upload`) or a stream (`end_source`, what the gRPC handler calls) ending
    with durability=always: its fsync runs on a worker thread, never blocking the event loop."""
    service = make_service(durability=Durability.ALWAYS)
    source = service.open_source(live=live)
    feeding.feed(service, source, iter_events(recordings["points"].path))
    on_loop: list[bool] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        try:
            asyncio.get_running_loop()
            on_loop.append(True)
        except RuntimeError:
            on_loop.append(False)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    end = service.finish_upload(source) if not live else service.end_source(source)
    report = asyncio.run(end)
    assert on_loop and not any(on_loop)
    assert service.runs[report.runs[0]].hot.dirty is False
    assert service.live_streams == 0


def test_disk_guard_refuses_before_writing(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service(min_free_bytes=1 << 62)
    with pytest.raises(InsufficientStorageError, match="FLEET_MIN_FREE_BYTES") as info:
        upload(service, recordings["points"].path)
    assert info.value.http_status() == 507
    assert not any(service.hot.root.iterdir())


def test_stream_limit(make_service: Factory):
    service = make_service(max_streams=2)
    a, b = service.open_source(live=True), service.open_source(live=True)
    with pytest.raises(ResourceExhaustedError, match=r"its limit \(FLEET_MAX_STREAMS\)") as info:
        service.open_source(live=True)
    assert info.value.grpc_status() == "RESOURCE_EXHAUSTED"
    service.close_source(a)
    service.close_source(service.open_source(live=True))
    service.close_source(b)
    assert service.live_streams == 0


def test_idle_live_run_is_closed(make_service: Factory, recordings: dict[str, Recording]):
    now = [dt.datetime(2026, 11, 21, 12, 0, tzinfo=dt.UTC)]
    service = make_service(close_after_s=30, clock=lambda: now[0])
    source = service.open_source(live=True)
    for event in iter_events(recordings["points"].path):
        service.accept(source, event)
    run_id = source.report.runs[0]
    now[0] += dt.timedelta(seconds=29)
    assert service.close_idle() == [] and service.runs[run_id].status == "live"
    now[0] += dt.timedelta(seconds=1)
    assert service.close_idle() == [run_id]
    assert catalog_run_after_flush(service, run_id)["status"] == "closed"
    # The idle stream speaks again (a chunk the run does not hold yet): the run is live again.
    more = next(e for e in iter_events(recordings["points"].path) if isinstance(e, ArrowMessage))
    service.runs[run_id].chunk_ids.discard(more.chunk_id)  # type: ignore[arg-type]
    service.accept(source, more)
    assert service.runs[run_id].status == "live"
    service.close_source(source)


def catalog_run_after_flush(service: IngestService, run_id: str) -> dict[str, Any]:
    service.flush_catalog()
    return catalog_run(service, run_id)


def test_errors_are_fleet_errors():
    for exc_type in (UnsafeIdError, InvalidArgumentError, ResourceExhaustedError, InsufficientStorageError):
        assert issubclass(exc_type, FleetError)


def test_several_recordings_in_one_source(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    merged = recordings["merged"]
    report = upload(service, merged.path)
    ids = [r["recording_id"] for r in merged.recordings]
    assert sorted(report.runs) == sorted(ids)
    by_store: dict[str, list[bytes]] = {}
    for event in iter_events(merged.path):
        if isinstance(event, ArrowMessage):
            by_store.setdefault(event.store_id.recording_id, []).append(event.chunk_id)  # type: ignore[arg-type]
    for run_id in ids:
        assert sorted(chunk_ids(service.runs[run_id].hot.path)) == sorted(by_store[run_id])


def _data_before_properties(events: list[Any]) -> list[Any]:
    """The recording's events with its property chunks after its first data chunk (as the SDK's
    batcher often sends them), so a run exists before its fleet property names its robot."""
    props = [e for e in events if isinstance(e, ArrowMessage) and chunk_meta(e).entity_path.startswith("/__properties")]
    rest = [e for e in events if not any(e is p for p in props)]
    first_data = next(i for i, e in enumerate(rest) if isinstance(e, ArrowMessage))
    return rest[: first_data + 1] + props + rest[first_data + 1 :]


def test_a_run_refused_for_its_robot_is_dropped_even_once_catalogued(
    make_service: Factory, recordings: dict[str, Recording]
):
    service = make_service()
    events = _data_before_properties(list(iter_events(recordings["properties"].path)))
    first_data = next(i for i, e in enumerate(events) if isinstance(e, ArrowMessage))
    stream = service.open_source(live=True, robot="robot-a")
    feeding.feed(service, stream, events[: first_data + 1])
    service.flush_catalog()
    assert catalog_run(service, "rec-properties")["robot_id"] == "robot-a"  # filed under the token's robot so far
    with pytest.raises(FleetError, match="robot 'robot-7'"):
        feeding.feed(service, stream, events[first_data + 1 :])
    service.close_source(stream)
    service.flush_catalog()
    assert service.hot_run("rec-properties") is None and list(service.hot.existing()) == []
    assert service.catalog is not None
    with session_scope(service.catalog) as session:
        assert queries.get_run(session, "rec-properties") is None
        assert queries.list_robots(session) == []  # robot-a had no other run
    own = service.open_source(live=False, robot="robot-7")
    feeding.feed(service, own, events)
    asyncio.run(service.finish_upload(own))
    assert catalog_run(service, "rec-properties")["robot_id"] == "robot-7"


def test_a_refused_robot_keeps_a_run_that_another_source_feeds(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    events = _data_before_properties(list(iter_events(recordings["properties"].path)))
    first_data = next(i for i, e in enumerate(events) if isinstance(e, ArrowMessage))
    robot_a, other = service.open_source(live=True, robot="robot-a"), service.open_source(live=True, robot="robot-a")
    feeding.feed(service, robot_a, events[: first_data + 1])
    feeding.feed(service, other, events[:first_data])  # attached to the same run, not its starter
    with pytest.raises(FleetError, match="robot 'robot-7'"):
        feeding.feed(service, robot_a, events[first_data + 1 :])
    assert service.hot_run("rec-properties") is not None  # another stream still feeds it: not dropped


def _properties_first(events: list[Any]) -> list[Any]:
    """The recording's events with its property chunks before its first data chunk (the SDK's
    batcher sends them so at times)."""
    props = [e for e in events if isinstance(e, ArrowMessage) and chunk_meta(e).entity_path.startswith("/__properties")]
    rest = [e for e in events if not any(e is p for p in props)]
    first_data = next(i for i, e in enumerate(rest) if isinstance(e, ArrowMessage))
    return rest[:first_data] + props + rest[first_data:]


@pytest.mark.parametrize("order", [_properties_first, _data_before_properties], ids=["property-first", "data-first"])
def test_a_refused_run_is_reported_dropped_whichever_chunk_came_first(
    make_service: Factory, recordings: dict[str, Recording], order: Any
):
    service = make_service()
    stream = service.open_source(live=False, robot="robot-a")
    with pytest.raises(FleetError, match="robot 'robot-7'"):
        feeding.feed(service, stream, order(list(iter_events(recordings["properties"].path))))
    report = stream.report
    assert (report.runs, report.dropped, report.chunks_new, report.bytes_new) == ([], ["rec-properties"], 0, 0)
    assert service.hot_run("rec-properties") is None and list(service.hot.existing()) == []
