"""Secret-like fields are stripped from the properties of every store kind: a blueprint store's
`/__properties/NAME` chunk is filed without them, like a recording's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta, read_chunk
from tests.services.ingest import feeding
from tests.services.ingest.conftest import Factory
from tests.services.ingest.secrets_scan import places_holding

pytestmark = pytest.mark.sdk

SECRET = "blueprint-secret-4242"
# A blueprint whose store also carries a property with a secret-like field (api_key).
SCRIPT = """
import sys
import rerun as rr
import rerun.blueprint as rrb

class WithProperty(rrb.Blueprint):
    def _log_to_stream(self, stream):
        super()._log_to_stream(stream)
        stream.send_property("notes", rr.AnyValues(api_key=sys.argv[2], owner="ops"))

rec = rr.RecordingStream("bp_app", recording_id="bp-run")
rec.save(sys.argv[1])
rec.log("/a", rr.Scalars([1.0]))
rec.send_blueprint(WithProperty(rrb.TimeSeriesView(origin="/")), make_active=True, make_default=True)
rec.flush()
rec.disconnect()
"""


def blueprint_with_secret(path: Path) -> Path:
    subprocess.run([sys.executable, "-c", SCRIPT, str(path), SECRET], check=True, timeout=120, capture_output=True)
    return path


def test_a_blueprint_property_is_filed_without_its_secret_fields(make_service: Factory, tmp_path: Path) -> None:
    source = blueprint_with_secret(tmp_path / "bp.rrd")
    service = make_service()
    report = feeding.upload(service, iter_events(source))
    hot = service.runs[report.runs[0]].hot.path
    notes = [
        e
        for e in iter_events(hot)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.BLUEPRINT
        if chunk_meta(e).entity_path == "/__properties/notes"
    ]
    assert len(notes) == 1  # kept, without its secret field
    assert {f.name for f in read_chunk(notes[0]).schema} == {"rerun.controls.RowId", "owner"}
    assert places_holding([source], [SECRET], open_catalogs=False)  # the SDK did send it
    assert places_holding([hot], [SECRET], open_catalogs=False) == []
