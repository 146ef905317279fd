"""Store ids of pre-0.25 SDKs (no application id outside SetStoreInfo) are completed per stream."""

from __future__ import annotations

import io
import subprocess
from pathlib import Path

import pytest

from services.rrd import ArrowMessage, MessageKind, RrdEncoder, StoreId, StoreKind, iter_events
from services.rrd.decoder import decode_message
from services.rrd.footer import read_footer
from services.rrd.messages import BlueprintActivationMessage, StoreInfoMessage, StreamStart
from services.rrd.pb import log_msg_pb2
from services.rrd.store_ids import StoreIdResolver
from tests.services.rrd.legacy import legacy_file, legacy_messages
from tests.services.rrd.recordings import Recording


def _store_ids(events: object) -> list[StoreId]:
    return [
        e.blueprint_id if isinstance(e, BlueprintActivationMessage) else e.store_id  # type: ignore[attr-defined]
        for e in events  # type: ignore[attr-defined]
        if isinstance(e, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage)
    ]


def test_resolver_fills_only_what_setstoreinfo_named():
    resolver = StoreIdResolver()
    bare = StoreId(StoreKind.RECORDING, "", "run-1")
    assert resolver.resolve(bare) is bare  # nothing learnt yet: left as it is
    info = StoreInfoMessage(0, 0, 0, b"", StoreId(StoreKind.RECORDING, "nav", "run-1"), None, "")
    resolver.complete(info)
    assert resolver.resolve(bare) == StoreId(StoreKind.RECORDING, "nav", "run-1")
    assert resolver.resolve(StoreId(StoreKind.BLUEPRINT, "", "run-1")).application_id == ""  # per kind
    assert resolver.resolve(StoreId(StoreKind.RECORDING, "", "run-2")).application_id == ""  # per recording
    full = StoreId(StoreKind.RECORDING, "other", "run-1")
    assert resolver.resolve(full) is full  # a complete id is never changed


@pytest.mark.slow
def test_decoder_completes_legacy_store_ids(recordings: dict[str, Recording], tmp_path: Path):
    rec = recordings["blueprint"]  # a recording and a blueprint store, with an activation
    legacy = legacy_file(rec.path, tmp_path / "legacy.rrd")
    raw_ids = [
        StoreId.from_proto(log_msg_pb2.ArrowMsg.FromString(raw).store_id)
        for kind, raw in legacy_messages(rec.path)
        if kind == MessageKind.ARROW_MSG
    ]
    assert raw_ids and all(not s.application_id for s in raw_ids)  # really the legacy shape
    assert _store_ids(iter_events(legacy)) == _store_ids(iter_events(rec.path))
    # the message bytes are kept exactly as sent
    legacy_raw = [bytes(e.raw) for e in iter_events(legacy) if isinstance(e, ArrowMessage)]
    assert legacy_raw == [raw for kind, raw in legacy_messages(rec.path) if kind == MessageKind.ARROW_MSG]


@pytest.mark.slow
def test_encoder_footer_names_the_complete_store(recordings: dict[str, Recording]):
    """Messages handed over one by one (as from gRPC, with no decoder to complete them)."""
    rec = recordings["blueprint"]
    version = next(e.version for e in iter_events(rec.path) if isinstance(e, StreamStart))
    sink = io.BytesIO()
    encoder = RrdEncoder(sink, version)
    for offset, (kind, raw) in enumerate(legacy_messages(rec.path)):
        encoder.write(decode_message(kind, raw, offset))
    encoder.finish()
    footer = read_footer(io.BytesIO(sink.getvalue()))
    assert footer is not None
    stores = {StoreId.from_proto(m.store_id) for m in footer.manifests}
    assert stores == {s for s in _store_ids(iter_events(rec.path))}
    assert all(s.application_id for s in stores)


@pytest.mark.sdk
def test_chunks_without_chunk_id_get_one_in_footer_files(
    recordings: dict[str, Recording], tmp_path: Path, rerun_bin: str
):
    """0.23 sent the chunk id only inside the Arrow payload; footer readers seek by ArrowMsg.chunk_id
    (`rerun rrd verify` panics without it), so written files carry it, the payload untouched."""
    rec = recordings["points"]
    legacy = legacy_file(rec.path, tmp_path / "legacy.rrd", drop_chunk_ids=True)
    out = tmp_path / "served.rrd"
    with open(out, "wb") as fh:
        encoder: RrdEncoder | None = None
        for event in iter_events(legacy):
            if isinstance(event, StreamStart):
                encoder = RrdEncoder(fh, event.version)
            elif isinstance(event, StoreInfoMessage | ArrowMessage) and encoder is not None:
                encoder.write(event)
        assert encoder is not None
        encoder.finish()
    written = [e for e in iter_events(out) if isinstance(e, ArrowMessage)]
    original = [e for e in iter_events(rec.path) if isinstance(e, ArrowMessage)]
    assert [e.chunk_id for e in written] == [e.chunk_id for e in original]
    assert [e.is_static for e in written] == [e.is_static for e in original]
    assert [bytes(e.payload) for e in written] == [bytes(e.payload) for e in original]
    verify = subprocess.run([rerun_bin, "rrd", "verify", str(out)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr[-3000:]
