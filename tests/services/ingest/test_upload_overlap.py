"""An upload that shares no chunk with a run already holding data of its recording id (rerun-sdk
0.23 has no set_sinks: its file copy is a second recording with other chunk ids) is warned about."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from services.rrd import iter_events
from tests.services.ingest import feeding
from tests.services.ingest.conftest import Factory

pytestmark = pytest.mark.sdk

SCRIPT = """
import sys
import rerun as rr
rec = rr.RecordingStream("twin_app", recording_id="twin-run")
rec.save(sys.argv[1])
for i in range(3):
    rec.set_time("frame", sequence=i)
    rec.log("/a", rr.Scalars([float(i)]))
rec.flush()
rec.disconnect()
"""


def recording(path: Path) -> Path:
    """The same scene under the same recording id: each call writes chunks with ids of its own."""
    subprocess.run([sys.executable, "-c", SCRIPT, str(path)], check=True, timeout=120, capture_output=True)
    return path


def test_an_upload_sharing_no_chunk_with_the_run_is_warned_about(make_service: Factory, tmp_path: Path) -> None:
    first, twin = recording(tmp_path / "first.rrd"), recording(tmp_path / "twin.rrd")
    service = make_service()
    assert feeding.upload(service, iter_events(first)).warnings == []  # a new run
    assert feeding.upload(service, iter_events(first)).warnings == []  # all its chunks already held
    report = feeding.upload(service, iter_events(twin))
    assert report.chunks_new > 0 and report.chunks_duplicate == 0
    assert len(report.warnings) == 1 and "'twin-run'" in report.warnings[0]
    assert "twice" in report.warnings[0] and report.to_dict()["warnings"] == report.warnings
