"""ROS 2 bags and Foxglove / JSON MCAP files, written by the real MCAP libraries (tests/compat/bags.py),
converted by the pinned Rerun CLI (`rerun mcap convert`) as the depot will convert uploads: one
entity per topic, every message's known value where Rerun's decoders put it. Then what the
converter does with the bad inputs the depot must survive: it exits 0 on most of them, so the depot
judges a conversion by its output and bounds it in time.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from tests.compat import bag_values as V
from tests.compat.bags import (
    FOXGLOVE_EXPECTED,
    JSON_EXPECTED,
    ROS2_EXPECTED,
    Expected,
    bag_files,
    chunk_spans,
    convert,
    write_foxglove_mcap,
    write_json_mcap,
    write_ros2_bag,
)
from tests.compat.rrd_contents import Chunk, message_counts, read_rrd, static_values, values

pytestmark = [pytest.mark.slow, pytest.mark.sdk]

PROPERTIES = "/__mcap_properties"  # RecordingInfo:start_time and McapStatistics:*, static
METADATA = "/__mcap_metadata"  # one static component per MCAP metadata record (Foxglove's `foxglove`)


def converted(rerun_bin: str, mcap: Path, rrd: Path, recording_id: str) -> list[Chunk]:
    """`mcap` converted cleanly (exit 0, no ERROR logged, `rerun rrd verify` passes): its chunks."""
    done = convert(rerun_bin, mcap, rrd, recording_id)
    assert done.returncode == 0 and " ERROR " not in done.stderr, done.stderr
    verified = subprocess.run([rerun_bin, "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert verified.returncode == 0, verified.stdout + verified.stderr
    chunks = read_rrd(rrd)
    assert {c.recording_id for c in chunks} == {recording_id}
    return chunks


def assert_values(chunks: list[Chunk], expected: dict[str, Expected], messages: range) -> None:
    for topic, want in expected.items():
        assert values(chunks, topic, want.component) == [want.row(i) for i in messages], topic


def test_a_ros2_bag_becomes_one_entity_per_topic_with_every_value(rerun_bin: str, tmp_path: Path) -> None:
    bag = write_ros2_bag(tmp_path / "run1", messages=4)
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["storage_identifier"] == "mcap" and metadata["relative_file_paths"] == ["run1_0.mcap"]
    topics = [t["topic_metadata"] for t in metadata["topics_with_message_count"]]
    assert {t["name"]: t["type"] for t in topics} == V.ROS2_TOPICS
    assert [p.name for p in bag_files(bag)] == ["run1_0.mcap"]

    chunks = converted(rerun_bin, bag / "run1_0.mcap", tmp_path / "run1.rrd", "run1")
    assert message_counts(chunks) == {PROPERTIES: 0, **dict.fromkeys(V.ROS2_TOPICS, 4)}
    assert_values(chunks, ROS2_EXPECTED, range(4))
    for topic, ros_type in V.ROS2_TOPICS.items():  # each topic's static MCAP schema and channel
        assert static_values(chunks, topic, "McapSchema:name") == [[ros_type]]
        assert static_values(chunks, topic, "McapChannel:topic") == [[topic]]
    assert static_values(chunks, PROPERTIES, "RecordingInfo:start_time") == [[V.START_NS]]


def test_a_split_bag_converts_file_by_file_into_one_recording(rerun_bin: str, tmp_path: Path) -> None:
    """`rerun mcap convert` takes one file: a split bag is converted per file, same recording id."""
    bag = write_ros2_bag(tmp_path / "run2", messages=5, split=2)
    files = bag_files(bag)
    listed = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert [p.name for p in files] == listed["relative_file_paths"] == ["run2_0.mcap", "run2_1.mcap"]

    parts = [converted(rerun_bin, mcap, tmp_path / f"{mcap.stem}.rrd", "run2") for mcap in files]
    assert [message_counts(p)[V.CHATTER_TOPIC] for p in parts] == [3, 2]
    chunks = [c for part in parts for c in part]
    assert message_counts(chunks) == {PROPERTIES: 0, **dict.fromkeys(V.ROS2_TOPICS, 5)}
    assert_values(chunks, ROS2_EXPECTED, range(5))


def test_a_foxglove_mcap_keeps_its_values_and_metadata(rerun_bin: str, tmp_path: Path) -> None:
    mcap = write_foxglove_mcap(tmp_path / "fg.mcap")
    chunks = converted(rerun_bin, mcap, tmp_path / "fg.rrd", "fg")
    assert message_counts(chunks) == {
        METADATA: 0,
        PROPERTIES: 0,
        **dict.fromkeys(V.FOXGLOVE_TOPICS, V.FOXGLOVE_MESSAGES),
    }
    assert_values(chunks, FOXGLOVE_EXPECTED, range(V.FOXGLOVE_MESSAGES))
    assert static_values(chunks, METADATA, "foxglove") == [[[{"first": "deviceName", "second": V.DEVICE_NAME}]]]


def test_a_json_channel_falls_back_to_raw_message_bytes(rerun_bin: str, tmp_path: Path) -> None:
    mcap = write_json_mcap(tmp_path / "status.mcap")
    chunks = converted(rerun_bin, mcap, tmp_path / "status.rrd", "status")
    assert message_counts(chunks) == {PROPERTIES: 0, V.JSON_TOPIC: V.JSON_MESSAGES}
    assert_values(chunks, JSON_EXPECTED, range(V.JSON_MESSAGES))
    assert static_values(chunks, V.JSON_TOPIC, "McapSchema:encoding") == [["jsonschema"]]


def test_bad_inputs_exit_0_unless_hung_so_the_output_is_what_counts(rerun_bin: str, tmp_path: Path) -> None:
    """Rerun 0.41: a truncated MCAP converts to an empty recording with exit 0 (an ERROR on stderr);
    with --recover, every complete chunk before the cut. A .mcap that is no MCAP: exit 0, empty.
    A chunk whose records do not parse: the converter spins forever (a timeout must stop it)."""
    bag = write_ros2_bag(tmp_path / "cut", messages=40, chunk_size=2048)
    mcap = bag / "cut_0.mcap"
    spans = chunk_spans(mcap)
    assert len(spans) > 4
    start, length = spans[len(spans) // 2]
    data = mcap.read_bytes()

    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: start + length // 2])
    done = convert(rerun_bin, truncated, tmp_path / "t.rrd", "t")
    assert done.returncode == 0 and "MCAP summary is missing or corrupt" in done.stderr
    assert not any(message_counts(read_rrd(tmp_path / "t.rrd")).values())
    done = convert(rerun_bin, truncated, tmp_path / "r.rrd", "r", "--recover")
    assert done.returncode == 0 and " ERROR " not in done.stderr, done.stderr
    recovered = read_rrd(tmp_path / "r.rrd")
    kept = message_counts(recovered)[V.CHATTER_TOPIC]
    assert 0 < kept < 40
    assert values(recovered, V.CHATTER_TOPIC, "TextDocument:text") == [[V.chatter_text(i)] for i in range(kept)]

    not_mcap = tmp_path / "not.mcap"
    not_mcap.write_bytes(b"plain text, not an MCAP file\n" * 10)
    done = convert(rerun_bin, not_mcap, tmp_path / "n.rrd", "n")
    assert done.returncode == 0 and "Not an MCAP file" in done.stderr
    assert read_rrd(tmp_path / "n.rrd") == []

    corrupt = bytearray(data)
    for k in range(start + length // 2, start + length // 2 + 16):
        corrupt[k] ^= 0xFF
    (tmp_path / "corrupt.mcap").write_bytes(corrupt)
    try:
        done = convert(rerun_bin, tmp_path / "corrupt.mcap", tmp_path / "c.rrd", "c", timeout=5)
    except subprocess.TimeoutExpired:
        return  # what 0.41 does
    assert done.returncode != 0 or " ERROR " in done.stderr, "a corrupt chunk converted silently"
