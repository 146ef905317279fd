"""The real Rerun 0.41 viewer, headless, opening a dataset snapshot's version from the depot (auth on):
the server page lists `picks:1`, its page lists its episodes (two windows of one sealed run, which
share chunks), and a window opens whole: its manifest and its chunks, under ids of its own."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from tests.services.redap.depots import serving
from tests.services.redap.test_viewer_depot import read_token
from tests.services.redap.test_viewer_reference import downloaded, lists
from tests.services.rrd.recordings import Recording
from tests.viewer import HeadlessViewer, assert_not_blank

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

RUN = "rec-points"  # frames 100 to 105 in two chunks of each entity, sealed by `serving`


def test_the_viewer_opens_a_window_of_a_snapshot(recordings: dict[str, Recording], rerun_bin: str, tmp_path: Path):
    with serving(recordings, tmp_path / "data", auth="on") as server:
        for frame in (101, 104):
            made = httpx.post(
                f"{server.url}/v1/runs/{RUN}/events",
                json={"timeline": "frame", "start": frame, "kind": "pick"},
                headers=server.headers,
                timeout=30,
            )
            assert made.status_code == 200, made.text
        window = {"event": ["pick"], "before_s": 0, "after_s": 0}
        body = {"name": "picks", "application": ["fleet_points"], "event_window": window}
        created = httpx.post(f"{server.url}/v1/datasets", json=body, headers=server.headers, timeout=60)
        assert created.status_code == 201 and created.json()["episodes"] == 2, created.text
        token = read_token(server.url, (tmp_path / "data" / "admin.token").read_text().strip())
        origin = f"rerun+http://127.0.0.1:{server.grpc_port}"
        with HeadlessViewer(rerun_bin, tmp_path / "viewer", env={"REDAP_TOKEN": token}).start() as viewer:
            viewer.open(f"{origin}/catalog")
            picks = viewer.wait_for_entries(origin, {"picks:1"}).value["picks:1"]
            viewer.open(picks.dataset_url)
            segments = {f"{RUN}~0", f"{RUN}~1"}
            viewer.wait_for_texts("Entry page", lists(segments, counted="segments"), "the episodes")
            at = viewer.open(picks.segment_url(f"{RUN}~1"))
            recording = viewer.wait_for_recording(f"{RUN}~1", at).value
            viewer.wait_for_texts("Selection panel", downloaded, "the window downloaded whole")
            schema = viewer.client.get_recording_schema(recording.store_id, paths_only=True)
            assert "/world/points" in {e.entity_path for e in schema.entities}
            assert_not_blank(viewer.screenshot("window"))
            assert not [line for line in viewer.errors(at) if "Chunk" in line or "failed" in line.lower()]
