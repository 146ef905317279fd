"""The table of component types Rerun knows (services/rrd/known_components.py): that of the pinned
rerun-sdk, and what every SDK of the compatibility matrix writes (so a chunk of an older robot is
never refused for a type it was right to write)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from services.rrd import known_components
from services.rrd.migrations import _COMPONENT_TYPE_RENAMES
from tests.compat.sdk_venvs import MATRIX, PINNED, sdk_bin

pytestmark = pytest.mark.sdk

DUMP = """
import json
import rerun.components as components
try:
    import rerun.blueprint.components as blueprint
except ImportError:
    blueprint = None
found = {}
for module in [m for m in (components, blueprint) if m is not None]:
    for name, batch in vars(module).items():
        if not (name.endswith("Batch") and hasattr(batch, "_ARROW_DATATYPE")):
            continue
        component_type = getattr(batch, "_COMPONENT_TYPE", None)  # 0.24 on
        if component_type is None and hasattr(batch, "_COMPONENT_DESCRIPTOR"):  # 0.23
            component_type = batch._COMPONENT_DESCRIPTOR.component_name
        if component_type is not None:
            found[str(component_type)] = str(batch._ARROW_DATATYPE)
print(json.dumps(found))
"""


def test_the_table_is_the_pinned_sdks() -> None:
    assert known_components.SDK_VERSION == PINNED
    text = Path(known_components.__file__).read_text()
    assert known_components.generated_source() == text, "stale: python -m services.rrd.known_components --write"


@pytest.mark.slow
@pytest.mark.parametrize("version", [v for v in MATRIX if v != PINNED])
def test_what_each_sdk_writes_fits_the_table(version: str) -> None:
    done = subprocess.run(
        [str(sdk_bin(version, "python")), "-c", DUMP], capture_output=True, text=True, timeout=300, check=True
    )
    written = json.loads(done.stdout)
    renamed = {old.decode(): new.decode() for _, renames in _COMPONENT_TYPE_RENAMES for old, new in renames.items()}
    expected = known_components.expected_types()
    checked = 0
    for component_type, written_type in written.items():
        current = renamed.get(component_type, component_type)  # as Rerun migrates it, and so do we
        if current not in expected:
            continue  # a type Rerun no longer knows: not checked
        assert str(expected[current]) == written_type, (version, component_type, written_type, expected[current])
        checked += 1
    assert checked > 100, f"rerun-sdk {version}: only {checked} component types compared"
