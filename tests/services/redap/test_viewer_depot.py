"""The real Rerun 0.41 viewer, headless, browsing the depot with auth on (its token in REDAP_TOKEN,
as a user gives it): the server page lists the fleet's datasets, a dataset's page is a table of its
runs with the fleet's columns, and runs open and draw, a sealed (warm) one and a hot one alike.

The same steps as against Rerun's own server (test_viewer_reference.py). Screenshots are kept under
the test's tmp dir (their paths are printed, with each step's time)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path
from typing import Any

import pytest

from tests.services.ingest.live_server import FLEET
from tests.services.redap.depots import serving
from tests.services.redap.test_viewer_reference import downloaded, lists, step, truth
from tests.services.rrd.recordings import Recording
from tests.viewer import HeadlessViewer, assert_not_blank, changed_share

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

WARM = "points"  # sealed into the warm tier by `serving`
HOT = "properties"  # left hot: opened from the hot chunk index
FLEET_COLUMNS = {"property:depot:robot_id", "property:depot:tier", "property:depot:status"}


def read_token(server_url: str, admin: str) -> str:
    made = subprocess.run(
        [FLEET, "tokens", "create", "--scope", "read", "--name", "viewer", "--api-url", server_url],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "FLEET_TOKEN": admin},
    )
    assert made.returncode == 0, made.stderr
    return made.stdout.strip()


def test_the_viewer_browses_the_depot_and_opens_warm_and_hot_runs(
    recordings: dict[str, Recording], rerun_bin: str, tmp_path: Path
) -> None:
    timings: dict[str, float] = {}
    with serving(recordings, tmp_path / "data", auth="on") as server:
        token = read_token(server.url, (tmp_path / "data" / "admin.token").read_text().strip())
        origin = f"rerun+http://127.0.0.1:{server.grpc_port}"
        applications = {truth(recordings[scene])["application_id"] for scene in (WARM, HOT)}
        viewer = HeadlessViewer(rerun_bin, tmp_path / "viewer", env={"REDAP_TOKEN": token})
        with step("start", timings):
            viewer.start()
        with viewer:
            print(f"viewer screenshots in {viewer.screenshots}")
            empty = viewer.screenshot("empty")
            with step("catalog", timings):
                viewer.open(f"{origin}/catalog")
                entries = viewer.wait_for_entries(origin, applications).value
                viewer.wait_for_texts("Server page", lambda texts: applications <= set(texts), "the datasets")
                catalog = viewer.screenshot("catalog")
            assert_not_blank(catalog)
            assert changed_share(empty, catalog) > 0.01

            opened: dict[str, Path] = {}
            for scene in (WARM, HOT):
                shown = truth(recordings[scene])
                dataset = entries[shown["application_id"]]
                segment_id = shown["recording_id"]
                with step(f"dataset {scene}", timings):
                    viewer.open(dataset.dataset_url)
                    viewer.wait_for_texts("Entry page", lists({segment_id}, counted="segments"), "the runs")
                    columns = {c.name for c in viewer.client.get_table_schema()}
                assert {"rerun_segment_id", *FLEET_COLUMNS} <= columns, columns
                with step(f"segment {scene}", timings):
                    at = viewer.open(dataset.segment_url(segment_id))
                    recording = viewer.wait_for_recording(segment_id, at).value
                    viewer.wait_for_texts("Selection panel", downloaded, "the run downloaded whole")
                    schema = viewer.client.get_recording_schema(recording.store_id, paths_only=True)
                    opened[scene] = viewer.screenshot(f"segment-{scene}")
                logged = {p for p in shown["entities"] if not p.startswith("/__properties")}
                assert logged <= {e.entity_path for e in schema.entities}
                assert_not_blank(opened[scene])
                assert all(not v.reports for v in viewer.snapshot().state.views)
            assert not any("Unauthenticated" in line for line in viewer.errors())
    print(f"viewer steps: {', '.join(f'{k} {v:.2f} s' for k, v in timings.items())}")


def test_the_viewer_without_a_token_is_refused(recordings: dict[str, Any], rerun_bin: str, tmp_path: Path) -> None:
    with serving(recordings, tmp_path / "data", auth="on") as server:
        origin = f"rerun+http://127.0.0.1:{server.grpc_port}"
        with HeadlessViewer(rerun_bin, tmp_path / "viewer").start() as viewer:
            viewer.open(f"{origin}/catalog")

            def refused() -> str | None:
                found = viewer.snapshot().server(origin)
                return found.error if found is not None and found.error else None

            error = viewer.wait_until(refused, "the catalog's refusal").value
        assert "Unauthenticated" in error or "no token" in error, error
