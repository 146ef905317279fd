"""Real recordings written by rerun-sdk, generated once per test session.

Names (keys of the `recordings` fixture):
  points, image, scalars, textlogs, transforms, static, properties  one recording each, with footer
  blueprint   a blueprint store and a recording store, BlueprintActivationCommand, footer with 2 manifests
  no_footer   FileSink(write_footer=False): no End message
  merge_a, merge_b, merged   two recordings and `rerun rrd merge` of both (one stream, 2 manifests)
  optimized   `rerun rrd optimize points.rrd`: one chunk per entity, with null cells
  cut         `points` cut in the middle of the payload of its 3rd ArrowMsg
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.services.rrd.recordings import (
    FOOTER_FILES,
    SCENES,
    SDK_FILES,
    WHOLE_FILES,
    Recording,
    cut_mid_arrow,
    generate_scenes,
    rerun_rrd,
)

CUT_ARROW_INDEX = 2


@pytest.fixture(scope="session")
def recordings_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("recordings")


@pytest.fixture(scope="session")
def recordings(rerun_bin: str, recordings_dir: Path) -> dict[str, Recording]:
    recs = generate_scenes(SCENES, recordings_dir)
    recs["merged"] = rerun_rrd(rerun_bin, "merge", [recs["merge_a"], recs["merge_b"]], recordings_dir, "merged")
    recs["optimized"] = rerun_rrd(rerun_bin, "optimize", [recs["points"]], recordings_dir, "optimized")
    recs["cut"] = cut_mid_arrow(recs["points"], recordings_dir, "cut", CUT_ARROW_INDEX)
    return recs


@pytest.fixture(scope="session", params=WHOLE_FILES)
def whole(request: pytest.FixtureRequest, recordings: dict[str, Recording]) -> Recording:
    """Each recording that decodes without error."""
    return recordings[request.param]


@pytest.fixture(scope="session", params=SDK_FILES)
def sdk_file(request: pytest.FixtureRequest, recordings: dict[str, Recording]) -> Recording:
    """Each file written directly by the SDK."""
    return recordings[request.param]


@pytest.fixture(scope="session", params=FOOTER_FILES)
def footer_file(request: pytest.FixtureRequest, recordings: dict[str, Recording]) -> Recording:
    """Each recording that ends with End and a footer manifest written by Rerun."""
    return recordings[request.param]
