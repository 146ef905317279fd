"""The real Rerun 0.41 viewer, headless, browsing Rerun's own catalog server (`rerun server`): the
server page, a dataset's segment table, then one segment loaded and drawn. What each step must show
is what a catalog server has to make the viewer show; the same steps run against the depot once it
serves the catalog.

Screenshots are kept under the test's tmp dir (their paths are printed, with each step's time)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from tests.services.rrd.recordings import Recording
from tests.viewer import HeadlessViewer, assert_not_blank, changed_share, image_stats
from tests.viewer_widgets import shown_after, table_rows

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

DATASET = "robots"  # holds both recordings: a segment table of two rows
OTHER = "solo"  # a second dataset, so the server page lists more than one entry
SHOWN = "points"  # the segment opened


@contextmanager
def step(name: str, timings: dict[str, float]) -> Iterator[None]:
    started = time.monotonic()
    yield
    timings[name] = time.monotonic() - started
    print(f"viewer step {name}: {timings[name]:.2f} s")


def truth(recording: Recording) -> dict[str, Any]:
    (one,) = recording.recordings
    return one


def timelines(recording: Recording) -> dict[str, tuple[int, int]]:
    """Each timeline the recording's entities were logged on, with its range."""
    ranges: dict[str, tuple[int, int]] = {}
    for entity in truth(recording)["entities"].values():
        for name, t in entity["timelines"].items():
            lo, hi = ranges.get(name, (t["min"], t["max"]))
            ranges[name] = (min(lo, t["min"]), max(hi, t["max"]))
    return ranges


def lists(names: set[str], counted: str | None = None) -> Callable[[list[str]], bool]:
    """A page's table shows a row for each of `names` and no other (its footer's row count), and
    the page's own count ("N segments") agrees if `counted` names it."""

    def holds(texts: list[str]) -> bool:
        count = texts[texts.index(counted) - 1] if counted in texts else None
        return names <= set(texts) and table_rows(texts) == len(names) and count in (None, str(len(names)))

    return holds


def downloaded(texts: list[str]) -> bool:
    return shown_after(texts, "Downloaded") == "100%"


def test_the_viewer_shows_the_catalog_a_dataset_and_a_segment_of_the_reference_server(
    reference_server: Any, recordings: dict[str, Recording], rerun_bin: str, tmp_path: Path
) -> None:
    both = [recordings["points"], recordings["scalars"]]
    server = reference_server({DATASET: both, OTHER: [recordings["scalars"]]})
    origin = f"rerun+http://127.0.0.1:{server.port}"
    segment_ids = [truth(r)["recording_id"] for r in both]
    timings: dict[str, float] = {}

    viewer = HeadlessViewer(rerun_bin, tmp_path / "viewer")
    with step("start", timings):
        viewer.start()
    with viewer:
        print(f"viewer screenshots in {viewer.screenshots}")
        empty = viewer.screenshot("empty")
        assert_not_blank(empty)  # the viewer's own UI renders on the software Vulkan driver

        with step("catalog", timings):
            viewer.open(f"{origin}/catalog")
            entries = viewer.wait_for_entries(origin, {DATASET, OTHER}).value
            page = viewer.wait_for_texts("Server page", lists({DATASET, OTHER}), "the datasets").value
            catalog = viewer.screenshot("catalog")
        assert {e.kind for e in entries.values()} == {"ENTRY_KIND_DATASET"}
        assert "Dataset" in page  # the entries table, not "Loading table"
        assert_not_blank(catalog)
        assert changed_share(empty, catalog) > 0.01

        dataset = entries[DATASET]
        with step("dataset", timings):
            viewer.open(dataset.dataset_url)
            rows = lists(set(segment_ids), counted="segments")
            page = viewer.wait_for_texts("Entry page", rows, "the segments").value
            columns = {c.name for c in viewer.client.get_table_schema()}
            shown_at = viewer.snapshot().state.location
            segments = viewer.screenshot("dataset")
        assert shown_at == dataset.dataset_url
        bounds = {f"{t}:{end}" for r in both for t in timelines(r) for end in ("start", "end")}
        assert {"rerun_segment_id", "rerun_num_chunks", *bounds} <= columns
        assert_not_blank(segments)
        assert changed_share(catalog, segments) > 0.01

        shown = recordings[SHOWN]
        segment_id = truth(shown)["recording_id"]
        first, last = timelines(shown)["frame"]
        with step("segment", timings):
            opened = viewer.open(dataset.segment_url(segment_id))
            recording = viewer.wait_for_recording(segment_id, opened).value
            # The recording's figures, as the user reads them. The viewer fetches chunks around its
            # time cursor as it plays the recording through: moving the cursor first would skip some.
            panel = viewer.wait_for_texts("Selection panel", downloaded, "the segment downloaded whole").value
            viewer.client.set_time("frame", sequence=last, play_state="paused")  # every point drawn, still
            schema = viewer.client.get_recording_schema(recording.store_id, paths_only=True)

            def spatial_view() -> Any | None:
                return next((v for v in viewer.snapshot().state.views if v.view_class == "3D"), None)

            spatial = viewer.wait_until(spatial_view, "the blueprint's 3D view").value

            def drawn() -> Path | None:
                shot = viewer.screenshot("segment-3d", spatial.view_id)
                return shot if image_stats(shot).chromatic > 0 else None  # the points are coloured, the grid grey

            viewer.wait_until(drawn, "the 3D view to draw the points")

            whole = viewer.screenshot("segment")
            views = viewer.snapshot().state.views
        assert {(t.name, t.start, t.end) for t in recording.timelines if t.name == "frame"} == {("frame", first, last)}
        assert set(truth(shown)["entities"]) <= {e.entity_path for e in schema.entities}
        assert all(not v.reports for v in views), [v.reports for v in views]
        assert shown_after(panel, "Segment ID") == segment_id
        assert_not_blank(whole)
        assert changed_share(segments, whole) > 0.01

    print(f"viewer steps: {', '.join(f'{k} {v:.2f} s' for k, v in timings.items())}")
