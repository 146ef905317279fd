"""No run can poison the catalog: long names the SDK makes are stored, names no catalog can hold
(NUL, too long) are refused before anything is written, property values are plain JSON, and a
record the catalog refuses waits alone while every other run is written, at runtime and at restart.
Run on embedded DuckDB and on a real Postgres."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from core.clock import utcnow
from core.errors import InvalidArgumentError
from core.ids import NAME_BYTES, PATH_BYTES
from services.ingest.service import IngestService
from services.rrd import StoreInfoMessage, iter_events
from services.rrd.decoder import decode_message
from services.rrd.messages import Event
from services.rrd.pb import log_msg_pb2
from services.runs.service import RunFilter, list_runs
from tests.services.ingest import feeding
from tests.services.ingest.factory import ingest_service

pytestmark = pytest.mark.sdk

LONG = "t" * 300  # over the old VARCHAR(256) columns


def log(
    path: Path,
    *,
    application: str,
    recording_id: str,
    timeline: str = "frame",
    properties: str = "rr.AnyValues(site='lab')",
) -> Path:
    script = f"""
import rerun as rr
rec = rr.RecordingStream({application!r}, recording_id={recording_id!r})
rec.save({str(path)!r})
rec.send_property('fleet', {properties})
for i in range(3):
    rec.set_time({timeline!r}, sequence=i)
    rec.log('/world/speed', rr.Scalars(i * 0.5))
rec.flush()
"""
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120, capture_output=True)
    return path


def service(tmp_path: Path, catalog: sessionmaker[Session]) -> IngestService:
    return ingest_service(tmp_path, catalog)


def with_application(event: Event, application: str, recording_id: str) -> Event:
    """`event` as if another writer had named the store so (SetStoreInfo re-encoded)."""
    if not isinstance(event, StoreInfoMessage):
        return event
    pb = log_msg_pb2.SetStoreInfo.FromString(bytes(event.raw))
    pb.info.store_id.application_id.id = application
    pb.info.store_id.recording_id = recording_id
    return decode_message(int(event.kind), pb.SerializeToString(), event.offset)


def runs(catalog: sessionmaker[Session], **filters: object) -> list[str]:
    with session_scope(catalog) as session:
        page, _ = list_runs(session, RunFilter(**filters))  # type: ignore[arg-type]
        return sorted(run.id for run in page)


def test_names_the_sdk_makes_are_stored_and_unusable_ones_refused_before_writing(
    tmp_path: Path, catalog: sessionmaker[Session]
):
    ingest = service(tmp_path, catalog)
    long_names = log(tmp_path / "long.rrd", application=LONG, recording_id="long-names", timeline=LONG)
    report = feeding.upload(ingest, iter_events(long_names))
    assert report.chunks_new > 0 and report.catalog == "updated"
    with session_scope(catalog) as session:
        run = queries.get_run(session, "long-names")
        logged = next(e.store_id.application_id for e in iter_events(long_names) if isinstance(e, StoreInfoMessage))
        assert run is not None and run.application_id == logged  # the SDK shortens very long ones itself
        assert LONG in [t.name for t in queries.run_timelines(session, "long-names")]
    # the longest names ingest accepts fit the columns and indexes of both catalogs
    widest = dataclasses.replace(
        ingest.runs["long-names"].record("r"),
        id="widest",
        application_id="a" * NAME_BYTES,
        timelines=[queries.TimelineRecord("n" * NAME_BYTES, "sequence", 0, 1)],
        entities=[queries.EntityRecord("/" + "e" * (PATH_BYTES - 1), 1, 0, 1, 1, [], [])],
    )
    with session_scope(catalog, write=True) as session:
        queries.save_run(session, widest, dt.datetime.now(dt.UTC))

    for name, kwargs in (
        ("huge-timeline", {"application": "ok", "timeline": "t" * 1100}),
        ("nul-timeline", {"application": "ok", "timeline": "fr\x00me"}),
    ):
        path = log(tmp_path / f"{name}.rrd", recording_id=name, **kwargs)  # type: ignore[arg-type]
        with pytest.raises(InvalidArgumentError, match=r"NUL character|over the limit"):
            feeding.upload(ingest, iter_events(path))
        assert name not in ingest.runs and not (tmp_path / "hot" / name).exists()  # nothing left behind
    # the 0.41 SDK renames an application id with a NUL; another writer may not
    events = [with_application(e, "app\x00x", "nul-app") for e in iter_events(long_names)]
    with pytest.raises(InvalidArgumentError, match="NUL character"):
        feeding.upload(ingest, events)
    assert "nul-app" not in ingest.runs
    # the catalog still takes every other run's writes
    ok = log(tmp_path / "ok.rrd", application="ok", recording_id="after-the-refusals")
    assert feeding.upload(ingest, iter_events(ok)).catalog == "updated"
    assert runs(catalog) == ["after-the-refusals", "long-names", "widest"]


def test_nan_and_nul_in_properties_break_no_query(tmp_path: Path, catalog: sessionmaker[Session]):
    ingest = service(tmp_path, catalog)
    odd = log(
        tmp_path / "odd.rrd",
        application="nav",
        recording_id="odd-values",
        properties="rr.AnyValues(robot_id='robot-7', battery=float('nan'), peak=float('inf'), note='a\\x00b')",
    )
    plain = log(tmp_path / "plain.rrd", application="nav", recording_id="plain-values")
    for path in (odd, plain):
        assert feeding.upload(ingest, iter_events(path)).catalog == "updated"
    with session_scope(catalog) as session:
        run = queries.get_run(session, "odd-values")
        assert run is not None
        fleet = json.loads(run.properties)["fleet"]
    assert (fleet["battery"], fleet["peak"], fleet["note"]) == ("NaN", "Infinity", "a\ufffdb")
    # property filters cast every row's JSON: one odd run must not break them for everyone
    assert runs(catalog, properties={"fleet.site": "lab"}) == ["plain-values"]
    assert runs(catalog, properties={"fleet.battery": "NaN"}) == ["odd-values"]


def test_a_record_the_catalog_refuses_waits_alone(
    tmp_path: Path, catalog: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
):
    # The service's time stands still: the refused run's retry (2 s on) is not reached however long
    # the uploads below take on a loaded machine.
    now = utcnow()
    ingest = ingest_service(tmp_path, catalog, clock=lambda: now)
    bad, good = (log(tmp_path / f"{n}.rrd", application="nav", recording_id=n) for n in ("bad-run", "good-run"))
    save_run = queries.save_run

    def refusing(session: Session, record: queries.RunRecord, now: dt.datetime) -> None:
        if record.id == "bad-run":  # as Postgres refuses a value it cannot store
            raise sa.exc.DataError("INSERT ...", {}, ValueError("value refused"))
        save_run(session, record, now)

    monkeypatch.setattr(queries, "save_run", refusing)
    assert feeding.upload(ingest, iter_events(bad)).catalog == "updated"  # the data is kept either way
    assert feeding.upload(ingest, iter_events(good)).catalog == "updated"
    assert runs(catalog) == ["good-run"]
    stuck = ingest.runs["bad-run"]
    assert stuck.dirty and stuck.catalog_failures >= 1 and stuck.catalog_retry_at is not None
    # it does not come back at every flush: others' writes are not slowed down by it
    assert "bad-run" not in [r.id for r in ingest.take_dirty_records()]

    ingest.hot.close()
    restarted = service(tmp_path, catalog)  # a restart recovers both runs and does not fail
    assert sorted(restarted.recover()) == ["bad-run", "good-run"]
    monkeypatch.setattr(queries, "save_run", save_run)  # the cause is fixed: the run is written at its retry
    restarted.runs["bad-run"].catalog_retry_at = None
    restarted.flush_catalog()
    assert runs(catalog) == ["bad-run", "good-run"]
