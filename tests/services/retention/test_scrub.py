"""`fleet catalog scrub-secrets`: a warm run filed with secret-like property fields (as a rerun-sdk
0.23 robot's token and blueprint properties were before ingest stripped them) is found by a dry run,
sealed again without them (same chunks otherwise, `rerun rrd verify` accepts it), and a second
scrub finds nothing."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import lz4.block
import pytest

from catalog import queries
from catalog.db import session_scope
from services.facts.identity import PropertyChunk, SecretFields
from services.ingest import service as ingest_service
from services.retention.promote import download_warm
from services.retention.scrub import scrub
from services.retention.service import promote_now
from services.rrd.chunk import chunk_meta
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage, Compression
from services.sealed.tiers import Tiers
from services.sealed.write import RECORDING
from tests.services.ingest import feeding
from tests.services.retention.conftest import NodeFactory

pytestmark = pytest.mark.sdk

TOKEN = b"fleet_SCRUBME_0123456789abcdef"
API_KEY = b"KEY-SCRUBME-456"
RUN = "scrub-run"

SCRIPT = f"""
import rerun as rr
rr.init("scrub_app", recording_id={RUN!r}, spawn=False)
rr.save({{path!r}})
rr.send_property("fleet", rr.AnyValues(robot_id="robot-9", token={TOKEN.decode()!r}))
rr.send_property("creds", rr.AnyValues(api_key={API_KEY.decode()!r}, site="lab"))
for i in range(5):
    rr.set_time("frame", sequence=i)
    rr.log("/world/points", rr.Points3D([[i, 0, 0], [0, i, 0]]))
"""


def chunk_bodies(path: Path) -> dict[bytes, bytes]:
    """Each chunk's id -> its Arrow payload, decompressed."""
    found = {}
    for event in iter_events(path):
        if isinstance(event, ArrowMessage):
            body = bytes(event.payload)
            if event.compression == Compression.LZ4:
                body = lz4.block.decompress(body, uncompressed_size=event.uncompressed_size)
            found[chunk_meta(event).chunk_id] = body
    return found


def holds_token(path: Path) -> bool:
    return any(TOKEN in body for body in chunk_bodies(path).values())


def warm_copy(tiers: Tiers, node_catalog: object, tmp_path: Path, name: str) -> Path:
    with session_scope(node_catalog) as session:  # type: ignore[arg-type]
        prefix = queries.lifecycle(session, RUN).prefix  # type: ignore[union-attr]
    out = tmp_path / name
    download_warm(tiers, f"{prefix}/{RECORDING}", out)
    return out


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_secrets_filed_before_are_found_then_sealed_away(
    tiers: Tiers, make_node: NodeFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, rerun_bin: str
) -> None:
    path = tmp_path / "run.rrd"
    subprocess.run([sys.executable, "-c", SCRIPT.format(path=str(path))], check=True, timeout=120)
    node = make_node(tiers)
    real = ingest_service.read_property_chunk  # type: ignore[attr-defined]

    def as_filed_before(msg: ArrowMessage, meta: object, secret_fields: SecretFields) -> PropertyChunk:
        read = real(msg, meta, secret_fields)  # type: ignore[arg-type]
        return PropertyChunk(msg, meta, read.name, read.values)  # type: ignore[arg-type]  # kept as sent

    monkeypatch.setattr(ingest_service, "read_property_chunk", as_filed_before)
    node.upload(path)
    promote_now(node.retention, RUN)
    monkeypatch.undo()
    before = chunk_bodies(warm_copy(tiers, node.catalog, tmp_path, "before.rrd"))
    assert any(TOKEN in body for body in before.values()) and any(API_KEY in body for body in before.values())
    secrets = SecretFields()

    dry = scrub(node.retention, secrets, dry_run=True, actor="alice")
    assert [(s.run_id, s.outcome) for s in dry] == [(RUN, "found")]
    assert "fleet" in dry[0].detail and "creds" in dry[0].detail and TOKEN.decode() not in dry[0].detail
    assert chunk_bodies(warm_copy(tiers, node.catalog, tmp_path, "dry.rrd")) == before  # a dry run changes nothing

    done = scrub(node.retention, secrets, dry_run=False, actor="alice")
    assert [(s.run_id, s.outcome) for s in done] == [(RUN, "scrubbed")]
    after_path = warm_copy(tiers, node.catalog, tmp_path, "after.rrd")
    after = chunk_bodies(after_path)
    assert set(after) == set(before)  # every chunk kept, by id
    assert not any(TOKEN in body or API_KEY in body for body in after.values())
    changed = {chunk for chunk in before if before[chunk] != after[chunk]}
    assert len(changed) == 2  # the two property chunks; every other chunk as it was
    assert all(b"lab" in after[chunk] or b"robot-9" in after[chunk] for chunk in changed)  # other fields kept
    check = subprocess.run([rerun_bin, "rrd", "verify", str(after_path)], capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    with session_scope(node.catalog) as session:
        objects = queries.run_objects(session, RUN)
        assert objects[RECORDING].size == after_path.stat().st_size
        events = [(e.action, e.actor) for e in queries.run_events(session, RUN)]
    assert ("scrub", "alice") in events

    again = scrub(node.retention, secrets, dry_run=False, actor="alice")
    assert [(s.run_id, s.outcome) for s in again] == [(RUN, "clean")]


LIVE = "scrub-live"


def filed_before(node_upload: Callable[[], object], monkeypatch: pytest.MonkeyPatch) -> None:
    """Run `node_upload` with ingest keeping property chunks as sent (as it did before it stripped them)."""
    real = ingest_service.read_property_chunk  # type: ignore[attr-defined]

    def as_filed_before(msg: ArrowMessage, meta: object, secret_fields: SecretFields) -> PropertyChunk:
        read = real(msg, meta, secret_fields)  # type: ignore[arg-type]
        return PropertyChunk(msg, meta, read.name, read.values)  # type: ignore[arg-type]

    monkeypatch.setattr(ingest_service, "read_property_chunk", as_filed_before)
    try:
        node_upload()
    finally:
        monkeypatch.undo()


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_hot_runs_closed_are_promoted_without_secrets_live_ones_left(
    tiers: Tiers, make_node: NodeFactory, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, rerun_bin: str
) -> None:
    closed_path, live_path = tmp_path / "closed.rrd", tmp_path / "live.rrd"
    subprocess.run([sys.executable, "-c", SCRIPT.format(path=str(closed_path))], check=True, timeout=120)
    live_script = SCRIPT.replace(repr(RUN), repr(LIVE)).format(path=str(live_path))
    subprocess.run([sys.executable, "-c", live_script], check=True, timeout=120)
    node = make_node(tiers)
    stream = node.ingest.open_source(live=True)

    def file_both() -> None:
        node.upload(closed_path)
        feeding.feed(node.ingest, stream, iter_events(live_path))  # a stream still open: the run is live

    filed_before(file_both, monkeypatch)
    hot_file = node.ingest.hot_run(RUN).path  # type: ignore[union-attr]
    live_file = node.ingest.hot_run(LIVE).path  # type: ignore[union-attr]
    before = chunk_bodies(hot_file)
    assert any(TOKEN in body for body in before.values()) and holds_token(live_file)
    secrets = SecretFields()

    dry = scrub(node.retention, secrets, dry_run=True, actor="alice")
    assert sorted((s.run_id, s.tier, s.outcome) for s in dry) == [(LIVE, "hot", "found"), (RUN, "hot", "found")]
    assert all(TOKEN.decode() not in s.detail for s in dry)
    assert chunk_bodies(hot_file) == before and node.ingest.hot_run(RUN) is not None  # nothing moved

    done = {s.run_id: s for s in scrub(node.retention, secrets, dry_run=False, actor="alice")}
    assert (done[RUN].tier, done[RUN].outcome) == ("hot", "scrubbed") and "promoted" in done[RUN].detail
    assert (done[LIVE].outcome, holds_token(live_file)) == ("skipped", True)
    assert "live" in done[LIVE].detail
    assert node.ingest.hot_run(RUN) is None and not hot_file.exists()  # sealed; the hot copy is gone
    warm = warm_copy(tiers, node.catalog, tmp_path, "warm.rrd")
    after = chunk_bodies(warm)
    assert set(after) == set(before) and not any(TOKEN in b or API_KEY in b for b in after.values())
    assert sum(before[chunk] != after[chunk] for chunk in before) == 2  # the two property chunks only
    check = subprocess.run([rerun_bin, "rrd", "verify", str(warm)], capture_output=True, text=True)
    assert check.returncode == 0, check.stderr

    again = {s.run_id: s.outcome for s in scrub(node.retention, secrets, dry_run=False, actor="alice")}
    assert again == {RUN: "clean", LIVE: "skipped"}  # the live run waits for its stream to close
    node.ingest.close_source(stream)
