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

import pytest

from tests.services.rrd.recordings import FOOTER_FILES, SDK_FILES, WHOLE_FILES, Recording


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
