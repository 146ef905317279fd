"""Writes the test MCAP files with the real MCAP libraries; run with the MCAP tools' venv python
(tests/compat/mcap_venv.py), which holds them, never with the project's (which does not):

    python tests/compat/bag_writers.py ros2 OUTDIR [--messages N] [--split K] [--image WxH] [--noise]
                                                                [--compression zstd|lz4|none] [--chunk-size BYTES]
    python tests/compat/bag_writers.py foxglove OUT.mcap
    python tests/compat/bag_writers.py json OUT.mcap

`ros2` leaves a folder as `ros2 bag record -s mcap` (Humble) does: OUTDIR/metadata.yaml and
OUTDIR/<name>_0.mcap.. (profile ros2, cdr messages, ros2msg schemas with their dependencies).
Each topic gets N messages; `--split K` spreads them over K files as rosbag2's splitting does.
`--image` and `--noise` (random pixels, which zstd cannot shrink) make the large bags of the
converter's throughput measure; the pixels are then no longer those of bag_values.image_pixels.

Why a script and not a module: the writers pull protobuf and the Foxglove schemas, which must not
enter the project's venv (tests/compat/bags.py runs this in a subprocess).
"""

from __future__ import annotations

import argparse
import json
import random
import sys
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make `tests.compat` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from tests.compat import bag_values as V
from tests.compat.ros2_msgdefs import msgdef


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}


def ros2_messages(i: int, width: int, height: int, noise: random.Random | None) -> dict[str, dict[str, Any]]:
    """Message i of every topic, as the dicts mcap_ros2 encodes."""
    t = V.log_time(i)
    pixels = noise.randbytes(width * height * 3) if noise else V.image_pixels(i, width, height)
    cloud = V.points_bytes(i)
    field = {"datatype": 7, "count": 1}  # PointField.FLOAT32
    return {
        V.IMAGE_TOPIC: {
            "header": {"stamp": _stamp(t), "frame_id": "camera"},
            "height": height,
            "width": width,
            "encoding": V.IMAGE_ENCODING,
            "is_bigendian": 0,
            "step": width * 3,
            "data": pixels,
        },
        V.POINTS_TOPIC: {
            "header": {"stamp": _stamp(t), "frame_id": "lidar"},
            "height": 1,
            "width": V.POINTS_PER_CLOUD,
            "fields": [{"name": n, "offset": 4 * k, **field} for k, n in enumerate("xyz")],
            "is_bigendian": False,
            "point_step": 12,
            "row_step": len(cloud),
            "data": cloud,
            "is_dense": True,
        },
        V.IMU_TOPIC: {
            "header": {"stamp": _stamp(t), "frame_id": "imu_link"},
            "orientation": dict(zip("xyzw", V.IMU_ORIENTATION, strict=True)),
            "orientation_covariance": [0.0] * 9,
            "angular_velocity": dict(zip("xyz", V.imu_angular_velocity(i), strict=True)),
            "angular_velocity_covariance": [0.0] * 9,
            "linear_acceleration": dict(zip("xyz", V.IMU_LINEAR_ACCELERATION, strict=True)),
            "linear_acceleration_covariance": [0.0] * 9,
        },
        V.TF_TOPIC: {
            "transforms": [
                {
                    "header": {"stamp": _stamp(t), "frame_id": V.TF_PARENT},
                    "child_frame_id": V.TF_CHILD,
                    "transform": {
                        "translation": dict(zip("xyz", V.tf_translation(i), strict=True)),
                        "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    },
                }
            ]
        },
        V.CHATTER_TOPIC: {"data": V.chatter_text(i)},
    }


def write_ros2(
    out: Path,
    messages: int,
    split: int,
    width: int,
    height: int,
    noise: bool,
    compression: str = "zstd",
    chunk_size: int = 1024 * 1024,
) -> None:
    # The tools' venv only (mcap_venv.py); the project's venv has none of them.
    from mcap.writer import CompressionType  # type: ignore[import-not-found, unused-ignore]
    from mcap_ros2.writer import Writer  # type: ignore[import-not-found]

    out.mkdir(parents=True, exist_ok=True)
    rng = random.Random(7) if noise else None
    names = [f"{out.name}_{k}.mcap" for k in range(split)]
    files: list[dict[str, int]] = []
    for k, name in enumerate(names):
        indexes = [i for i in range(messages) if min(i * split // max(messages, 1), split - 1) == k]
        with open(out / name, "wb") as fh:
            writer = Writer(fh, chunk_size=chunk_size, compression=CompressionType[compression.upper()])
            schemas = {topic: writer.register_msgdef(t, msgdef(t)) for topic, t in V.ROS2_TOPICS.items()}
            for topic, schema in schemas.items():  # rosbag2 registers each topic with its QoS profiles
                writer._channel_ids[topic] = writer._writer.register_channel(
                    topic=topic, message_encoding="cdr", schema_id=schema.id, metadata={"offered_qos_profiles": ""}
                )
            for i in indexes:
                for seq_topic, message in ros2_messages(i, width, height, rng).items():
                    t = V.log_time(i)
                    writer.write_message(seq_topic, schemas[seq_topic], message, log_time=t, publish_time=t, sequence=i)
            writer.finish()
        first = V.log_time(indexes[0]) if indexes else V.START_NS
        last = V.log_time(indexes[-1]) if indexes else V.START_NS
        files.append({"start": first, "duration": last - first, "count": len(indexes) * len(V.ROS2_TOPICS)})
    (out / "metadata.yaml").write_text(rosbag2_metadata(names, files, messages))


def rosbag2_metadata(names: list[str], files: list[dict[str, int]], messages: int) -> str:
    """rosbag2's metadata.yaml (version 5, Humble), as its YAML emitter lays it out."""
    last = V.log_time(max(messages - 1, 0))
    lines = [
        "rosbag2_bagfile_information:",
        "  version: 5",
        "  storage_identifier: mcap",
        "  duration:",
        f"    nanoseconds: {last - V.START_NS}",
        "  starting_time:",
        f"    nanoseconds_since_epoch: {V.START_NS}",
        f"  message_count: {messages * len(V.ROS2_TOPICS)}",
        "  topics_with_message_count:",
    ]
    for topic, ros_type in V.ROS2_TOPICS.items():
        lines += [
            "    - topic_metadata:",
            f"        name: {topic}",
            f"        type: {ros_type}",
            "        serialization_format: cdr",
            '        offered_qos_profiles: ""',
            f"      message_count: {messages}",
        ]
    lines += ['  compression_format: ""', '  compression_mode: ""', "  relative_file_paths:"]
    lines += [f"    - {name}" for name in names]
    lines.append("  files:")
    for name, f in zip(names, files, strict=True):
        lines += [
            f"    - path: {name}",
            "      starting_time:",
            f"        nanoseconds_since_epoch: {f['start']}",
            "      duration:",
            f"        nanoseconds: {f['duration']}",
            f"      message_count: {f['count']}",
        ]
    return "\n".join(lines) + "\n"


def write_foxglove(path: Path) -> None:
    """Foxglove's protobuf schemas through mcap-protobuf-support, plus the `foxglove` metadata."""
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.Log_pb2 import Log  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.Pose_pb2 import Pose  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage  # type: ignore[import-not-found]
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3  # type: ignore[import-not-found]
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap_protobuf.writer import Writer  # type: ignore[import-not-found]

    with open(path, "wb") as fh, Writer(fh) as writer:
        writer.add_metadata("foxglove", {"deviceName": V.DEVICE_NAME})
        for i in range(V.FOXGLOVE_MESSAGES):
            t = V.log_time(i)
            stamp = Timestamp(seconds=t // 1_000_000_000, nanos=t % 1_000_000_000)
            x, y, z = V.tf_translation(i)
            messages: dict[str, Any] = {
                V.FG_TRANSFORM_TOPIC: FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=V.TF_PARENT,
                    child_frame_id=V.TF_CHILD,
                    translation=Vector3(x=x, y=y, z=z),
                    rotation=Quaternion(x=0, y=0, z=0, w=1),
                ),
                V.FG_LOG_TOPIC: Log(timestamp=stamp, level=Log.Level.INFO, message=V.log_text(i), name="planner"),
                V.FG_IMAGE_TOPIC: RawImage(
                    timestamp=stamp,
                    frame_id="camera",
                    width=V.IMAGE_WIDTH,
                    height=V.IMAGE_HEIGHT,
                    encoding=V.IMAGE_ENCODING,
                    step=V.IMAGE_WIDTH * 3,
                    data=V.image_pixels(i),
                ),
                V.FG_POINTS_TOPIC: PointCloud(
                    timestamp=stamp,
                    frame_id="lidar",
                    # Rerun 0.41 turns a cloud without a pose into null InstancePoses3D rows, which
                    # `rerun rrd verify` refuses: producers send one (identity here).
                    pose=Pose(position=Vector3(x=0, y=0, z=0), orientation=Quaternion(x=0, y=0, z=0, w=1)),
                    point_stride=12,
                    fields=[
                        PackedElementField(name=n, offset=4 * k, type=PackedElementField.FLOAT32)
                        for k, n in enumerate("xyz")
                    ],
                    data=V.points_bytes(i),
                ),
            }
            for topic, message in messages.items():
                writer.write_message(topic, message, log_time=t, publish_time=t, sequence=i)


def write_json(path: Path) -> None:
    """One jsonschema channel through the plain mcap writer."""
    from mcap.writer import Writer  # type: ignore[import-not-found, unused-ignore]

    schema = {
        "type": "object",
        "properties": {"battery": {"type": "number"}, "mode": {"type": "string"}, "seq": {"type": "integer"}},
    }
    with open(path, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="fleet-telemetry tests")
        schema_id = writer.register_schema(V.JSON_SCHEMA_NAME, "jsonschema", json.dumps(schema).encode())
        channel = writer.register_channel(V.JSON_TOPIC, "json", schema_id)
        for i in range(V.JSON_MESSAGES):
            t = V.log_time(i)
            data = json.dumps(V.json_status(i)).encode()
            writer.add_message(channel, log_time=t, data=data, publish_time=t, sequence=i)
        writer.finish()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="kind", required=True)
    ros2 = sub.add_parser("ros2")
    ros2.add_argument("out", type=Path)
    ros2.add_argument("--messages", type=int, default=3)
    ros2.add_argument("--split", type=int, default=1)
    ros2.add_argument("--image", default=f"{V.IMAGE_WIDTH}x{V.IMAGE_HEIGHT}")
    ros2.add_argument("--noise", action="store_true")
    ros2.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    ros2.add_argument("--chunk-size", type=int, default=1024 * 1024, help="MCAP chunk size (bytes)")
    for kind in ("foxglove", "json"):
        sub.add_parser(kind).add_argument("out", type=Path)
    args = parser.parse_args(argv)
    if args.kind == "ros2":
        width, height = (int(v) for v in args.image.split("x"))
        write_ros2(args.out, args.messages, args.split, width, height, args.noise, args.compression, args.chunk_size)
    elif args.kind == "foxglove":
        write_foxglove(args.out)
    else:
        write_json(args.out)


if __name__ == "__main__":
    main()
