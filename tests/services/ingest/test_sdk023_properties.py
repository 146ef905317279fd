"""rerun-sdk 0.23 writes field metadata as `rerun.kind` / `rerun.component` (a dot): its `fleet`
property's token is read (stream auth) and stripped, and its other properties are kept."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from services.facts.identity import fleet_claim, read_property_chunk
from services.rrd.chunk import chunk_meta, decompress_payload, read_chunk
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage, StoreKind
from tests.compat.sdk_venvs import sdk_bin

pytestmark = [pytest.mark.sdk]

TOKEN = "head023.body023.signature023"
SCRIPT = """
import sys, rerun as rr
rec = rr.RecordingStream("fleet_compat", recording_id="run-023")
rec.save(sys.argv[1])
rec.send_property("fleet", rr.AnyValues(robot_id="r023", token=sys.argv[2], site="lab"))
rec.log("/a", rr.Scalars([1.0]))
rec.flush(); rec.disconnect()
"""


def sdk023_recording(path: Path, token: str = TOKEN) -> Path:
    """A recording written by rerun-sdk 0.23 (its cached venv), with a `fleet` property holding `token`."""
    python = str(sdk_bin("0.23.4", "python"))
    subprocess.run([python, "-c", SCRIPT, str(path), token], check=True, timeout=120, capture_output=True)
    return path


def fleet_chunk(path: Path) -> ArrowMessage:
    for event in iter_events(path):
        if not isinstance(event, ArrowMessage) or event.store_id.kind != StoreKind.RECORDING:
            continue
        if chunk_meta(event).entity_path == "/__properties/fleet":
            return event
    raise AssertionError("no fleet property chunk")


def test_a_023_fleet_property_is_read_and_its_token_stripped(tmp_path: Path) -> None:
    msg = fleet_chunk(sdk023_recording(tmp_path / "r.rrd"))
    assert (read_chunk(msg).schema.field("token").metadata or {}).get(b"rerun.kind") == b"data"  # the 0.23 spelling
    claim = fleet_claim(msg, chunk_meta(msg))
    assert claim is not None and (claim.token, claim.robot) == (TOKEN, "r023")
    prop = read_property_chunk(msg, chunk_meta(msg))
    assert prop.values == {"robot_id": "r023", "site": "lab"}
    assert TOKEN.encode() not in decompress_payload(prop.message)
    assert prop.message.chunk_id == msg.chunk_id
