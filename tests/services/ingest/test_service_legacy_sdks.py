"""Ingest of streams as rerun-sdk 0.23/0.24 send them: chunk store ids without application id."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select

from catalog import models
from catalog.db import session_scope
from core.errors import InvalidArgumentError
from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.decoder import decode_message
from services.rrd.frames import MessageKind
from tests.services.ingest.conftest import Factory
from tests.services.ingest.test_service import catalog_run, chunk_ids, upload
from tests.services.rrd.legacy import legacy_file, legacy_messages
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk


def test_legacy_stream_is_filed_live(make_service: Factory, recordings: dict[str, Recording]):
    """gRPC hands over message by message (no RRD decoder): the service completes the ids."""
    rec = recordings["blueprint"]
    service = make_service()
    source = service.open_source(live=True)
    received = 0
    for kind, raw in legacy_messages(rec.path):
        service.accept(source, decode_message(kind, raw, received))
        received += len(raw)
    report = service.close_source(source)
    run_id = rec.recordings[0]["recording_id"]
    assert report.runs == [run_id]
    assert report.chunks_new == len(chunk_ids(rec.path))
    service.flush_catalog()
    run = catalog_run(service, run_id)
    assert run["application_id"] == rec.recordings[0]["application_id"]
    assert run["chunks"] == sum(
        1 for e in iter_events(rec.path) if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    )
    held = service.runs[run_id].hot.path
    assert sorted(chunk_ids(held)) == sorted(chunk_ids(rec.path))  # blueprint chunks kept with the run


def test_legacy_file_is_filed_by_upload(make_service: Factory, recordings: dict[str, Recording], tmp_path: Path):
    rec = recordings["points"]
    service = make_service()
    report = upload(service, legacy_file(rec.path, tmp_path / "legacy.rrd"))
    run_id = rec.recordings[0]["recording_id"]
    assert report.runs == [run_id] and report.chunks_new == len(chunk_ids(rec.path))
    assert catalog_run(service, run_id)["application_id"] == rec.recordings[0]["application_id"]


def test_refused_source_leaves_no_empty_run(make_service: Factory, recordings: dict[str, Recording]):
    """A stream refused at its first chunk (here: a chunk of a recording it never introduced) must
    not leave behind a run with no data, filed under the default robot."""
    rec = recordings["points"]
    service = make_service()
    messages = legacy_messages(rec.path)
    store_info = next(raw for kind, raw in messages if kind == MessageKind.SET_STORE_INFO)
    stray = next(e for e in iter_events(recordings["scalars"].path) if isinstance(e, ArrowMessage))
    source = service.open_source(live=False)
    with pytest.raises(InvalidArgumentError, match="before its SetStoreInfo"):
        service.accept(source, decode_message(MessageKind.SET_STORE_INFO, store_info))
        service.accept(source, stray)
    service.close_source(source)
    service.flush_catalog()
    assert service.catalog is not None
    with session_scope(service.catalog) as session:
        assert session.scalars(select(models.Run.id)).all() == []
