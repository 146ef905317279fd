"""Small real MCAP files and rosbag2 folders for the agent's bag tests, written with the `mcap`
package: one jsonschema/json channel, a few messages."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.writer import CompressionType, Writer

SCHEMA = {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}}}


def write_mcap(
    path: Path, messages: int = 3, *, finish: bool = True, start_ns: int = 1_700_000_000_000_000_000
) -> Path:
    """An MCAP file of `messages` poses on `/pose`; `finish=False` leaves it as a writer that is
    still recording (or crashed) leaves it: no summary, no footer, no trailing magic."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.NONE)
        writer.start(profile="", library="fleet-tests")
        schema = writer.register_schema(name="Pose", encoding="jsonschema", data=json.dumps(SCHEMA).encode())
        channel = writer.register_channel(topic="/pose", message_encoding="json", schema_id=schema)
        for i in range(messages):
            at = start_ns + i * 100_000_000
            writer.add_message(channel, log_time=at, data=json.dumps({"x": i, "y": -i}).encode(), publish_time=at)
        if finish:
            writer.finish()
    return path


def write_metadata(folder: Path, names: list[str], *, prefix_folder: bool = False) -> Path:
    """The `metadata.yaml` rosbag2 writes when it closes a bag, listing `names` (with the folder in
    front, as the oldest rosbag2 versions wrote them, if `prefix_folder`)."""
    listed = [f"{folder.name}/{n}" if prefix_folder else n for n in names]
    lines = [
        "rosbag2_bagfile_information:",
        "  version: 9",
        "  storage_identifier: mcap",
        "  duration:",
        "    nanoseconds: 200000000",
        "  starting_time:",
        "    nanoseconds_since_epoch: 1700000000000000000",
        f"  message_count: {3 * len(names)}",
        "  topics_with_message_count:",
        "    - topic_metadata:",
        "        name: /pose",
        "        type: geometry_msgs/msg/Pose",
        "        serialization_format: cdr",
        "      message_count: 3",
        '  compression_format: ""',
        '  compression_mode: ""',
        "  relative_file_paths:",
        *[f"    - {n}" for n in listed],
        "  files:",
        *[f"    - path: {n}\n      message_count: 3" for n in listed],
        "  custom_data: ~",
        "  ros_distro: jazzy",
    ]
    path = folder / "metadata.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


def write_bag(folder: Path, splits: int = 1, *, metadata: bool = True) -> list[Path]:
    """A closed rosbag2 bag: `FOLDER_0.mcap` ... `FOLDER_{splits-1}.mcap`, and its metadata.yaml."""
    files = [
        write_mcap(folder / f"{folder.name}_{i}.mcap", start_ns=1_700_000_000_000_000_000 + i) for i in range(splits)
    ]
    if metadata:
        write_metadata(folder, [f.name for f in files])
    return files
