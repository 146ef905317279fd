"""Test MCAP files written by the real MCAP libraries, from the project's venv: each function runs
tests/compat/bag_writers.py in the MCAP tools' venv (tests/compat/mcap_venv.py) and returns what it
wrote. With EXPECTED, what Rerun's `mcap convert` makes of each topic: the entity (the topic), the
component holding the topic's known value, and that value for message i, as rrd_contents.values()
reads it (one row: the list of its instances).

    bag = write_ros2_bag(tmp_path / "run1", messages=5)    # tmp_path/run1/{metadata.yaml, run1_0.mcap}
    for mcap in bag_files(bag):
        convert(rerun_bin, mcap, tmp_path / f"{mcap.stem}.rrd", "run1")
    chunks = rrd_contents.read_rrd(tmp_path / "run1_0.rrd")
    for topic, want in ROS2_EXPECTED.items():
        assert rrd_contents.values(chunks, topic, want.component) == [want.row(i) for i in range(5)]
    write_foxglove_mcap(tmp_path / "fg.mcap"); write_json_mcap(tmp_path / "status.mcap")

The topics, types and values themselves are in bag_values.py (FOXGLOVE_EXPECTED, JSON_EXPECTED alike).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.compat import bag_values as V
from tests.compat.mcap_venv import mcap_python

WRITER = Path(__file__).with_name("bag_writers.py")
APPLICATION_ID = "fleet-bag-tests"
MCAP_MAGIC = b"\x89MCAP0\r\n"


def write_ros2_bag(
    out: Path,
    messages: int = 3,
    split: int = 1,
    image: tuple[int, int] | None = None,
    noise: bool = False,
    chunk_size: int | None = None,
    compression: str = "zstd",
) -> Path:
    """A rosbag2 folder `out` (metadata.yaml and `<out.name>_0.mcap`..`_{split-1}`), each of the five
    topics of ROS2_TOPICS with `messages` messages. `image` (width, height) and `noise` are for
    large bags; with them the pixels are not EXPECTED's. `chunk_size` (bytes, default 1 MiB) and
    `compression` (zstd, lz4, none) shape the MCAP chunks."""
    args = ["ros2", str(out), "--messages", str(messages), "--split", str(split), "--compression", compression]
    if image is not None:
        args += ["--image", f"{image[0]}x{image[1]}"]
    if noise:
        args.append("--noise")
    if chunk_size is not None:
        args += ["--chunk-size", str(chunk_size)]
    _run(args)
    return out


def bag_files(bag: Path) -> list[Path]:
    """The bag's MCAP files in rosbag2's order (`_0`, `_1`, ... as metadata.yaml lists them)."""
    return sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))


def write_foxglove_mcap(path: Path) -> Path:
    """FOXGLOVE_MESSAGES messages on each of FOXGLOVE_TOPICS, and a `foxglove` metadata record."""
    _run(["foxglove", str(path)])
    return path


def write_json_mcap(path: Path) -> Path:
    """JSON_MESSAGES messages on JSON_TOPIC (jsonschema schema, json encoding)."""
    _run(["json", str(path)])
    return path


def native_rerun(rerun_bin: str) -> str:
    """The `rerun` executable itself. The venv's `rerun` is a Python shim that runs it as a child
    and passes no signal on: a timeout that kills the shim leaves a spinning converter behind."""
    spec = importlib.util.find_spec("rerun_cli")
    exe = Path(spec.origin).with_name("rerun") if spec is not None and spec.origin is not None else None
    return str(exe) if exe is not None and exe.is_file() and os.access(exe, os.X_OK) else rerun_bin


def convert(
    rerun_bin: str, mcap: Path, rrd: Path, recording_id: str, *extra: str, timeout: float = 300
) -> subprocess.CompletedProcess[str]:
    """`rerun mcap convert` as the depot runs it (explicit recording and application ids). Returns
    whatever it did: 0.41 exits 0 on a truncated file or a non-MCAP `.mcap` (an ERROR line on stderr,
    an empty recording), so callers judge its stderr and output. Some corrupt chunks make it spin
    forever: raises subprocess.TimeoutExpired (the converter killed) after `timeout` seconds."""
    cmd = [native_rerun(rerun_bin), "mcap", "convert", str(mcap), "-o", str(rrd)]
    cmd += ["--recording-id", recording_id, "--application-id", APPLICATION_ID, *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)


def chunk_spans(mcap: Path) -> list[tuple[int, int]]:
    """(offset, length) of each Chunk record of the data section, read from the record framing
    (opcode u8, length u64 LE) without the MCAP library, which only the tools' venv has."""
    data = mcap.read_bytes()
    spans, pos = [], len(MCAP_MAGIC)
    while pos + 9 <= len(data):
        opcode, length = data[pos], int.from_bytes(data[pos + 1 : pos + 9], "little")
        if opcode == 0x06:  # Chunk
            spans.append((pos, 9 + length))
        if opcode == 0x0F:  # DataEnd: the summary follows
            break
        pos += 9 + length
    return spans


def _run(args: list[str]) -> None:
    done = subprocess.run(
        [str(mcap_python()), str(WRITER), *args], capture_output=True, text=True, timeout=900, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"bag_writers.py {' '.join(args)} failed ({done.returncode}):\n{done.stderr[-3000:]}")


@dataclass(frozen=True)
class Expected:
    """Where a topic's known value lands in the RRD, and that value (one row) for message i."""

    component: str  # the Arrow column's `rerun:component`, e.g. "Transform3D:translation"
    row: Callable[[int], list[Any]]


def _xyz(v: tuple[float, ...]) -> list[float]:
    return list(v)


# The ROS 2 bag, by entity (= topic). Image pixels and float32 values compare exactly as written.
ROS2_EXPECTED = {
    V.IMAGE_TOPIC: Expected("Image:buffer", lambda i: [list(V.image_pixels(i))]),
    V.POINTS_TOPIC: Expected("Points3D:positions", lambda i: [_xyz(p) for p in V.points(i)]),
    V.IMU_TOPIC: Expected("Scalars:scalars", lambda i: [*V.imu_angular_velocity(i), *V.IMU_LINEAR_ACCELERATION]),
    V.TF_TOPIC: Expected("Transform3D:translation", lambda i: [_xyz(V.tf_translation(i))]),
    V.CHATTER_TOPIC: Expected("TextDocument:text", lambda i: [V.chatter_text(i)]),
}
FOXGLOVE_EXPECTED = {
    V.FG_TRANSFORM_TOPIC: Expected("Transform3D:translation", lambda i: [_xyz(V.tf_translation(i))]),
    V.FG_LOG_TOPIC: Expected("TextLog:text", lambda i: [V.log_text(i)]),
    V.FG_IMAGE_TOPIC: Expected("Image:buffer", lambda i: [list(V.image_pixels(i))]),
    V.FG_POINTS_TOPIC: Expected("Points3D:positions", lambda i: [_xyz(p) for p in V.points(i)]),
}
# No semantic decoder takes JSON: the raw fallback keeps each message's bytes.
JSON_EXPECTED = {
    V.JSON_TOPIC: Expected("McapMessage:data", lambda i: [list(json.dumps(V.json_status(i)).encode())]),
}
