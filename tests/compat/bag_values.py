"""What the test bags hold: topics, types and the value of every message, as plain functions of the
message's index.

Why a module of its own, stdlib only: the writers (bag_writers.py, run in the MCAP tools' venv) and
the tests (run in the project's venv) both import it, so what is asserted is what was written.
"""

from __future__ import annotations

import struct

START_NS = 1_700_000_000_000_000_000  # the first message's log time (and header stamp)
PERIOD_NS = 100_000_000  # one message per topic every 100 ms

# The ROS 2 bag: one entity per topic in the RRD.
IMAGE_TOPIC = "/camera/image"
POINTS_TOPIC = "/lidar/points"
IMU_TOPIC = "/imu"
TF_TOPIC = "/tf"
CHATTER_TOPIC = "/chatter"
ROS2_TOPICS = {
    IMAGE_TOPIC: "sensor_msgs/msg/Image",
    POINTS_TOPIC: "sensor_msgs/msg/PointCloud2",
    IMU_TOPIC: "sensor_msgs/msg/Imu",
    TF_TOPIC: "tf2_msgs/msg/TFMessage",
    CHATTER_TOPIC: "std_msgs/msg/String",
}
ROS_DISTRO = "jazzy"

IMAGE_WIDTH = 4
IMAGE_HEIGHT = 3
IMAGE_ENCODING = "rgb8"
POINTS_PER_CLOUD = 5
TF_PARENT = "map"
TF_CHILD = "base_link"

# The Foxglove (protobuf) MCAP.
FG_TRANSFORM_TOPIC = "/foxglove/transform"
FG_LOG_TOPIC = "/foxglove/log"
FG_IMAGE_TOPIC = "/foxglove/image"
FG_POINTS_TOPIC = "/foxglove/points"
FOXGLOVE_TOPICS = {
    FG_TRANSFORM_TOPIC: "foxglove.FrameTransform",
    FG_LOG_TOPIC: "foxglove.Log",
    FG_IMAGE_TOPIC: "foxglove.RawImage",
    FG_POINTS_TOPIC: "foxglove.PointCloud",
}
FOXGLOVE_MESSAGES = 3
DEVICE_NAME = "test-robot-7"

# The JSON MCAP.
JSON_TOPIC = "/status"
JSON_SCHEMA_NAME = "Status"
JSON_MESSAGES = 4


def log_time(i: int) -> int:
    return START_NS + i * PERIOD_NS


def image_pixels(i: int, width: int = IMAGE_WIDTH, height: int = IMAGE_HEIGHT) -> bytes:
    """rgb8, row-major: red counts columns, green rows, blue the message index."""
    return bytes(
        channel for y in range(height) for x in range(width) for channel in ((x * 10) % 256, (y * 20) % 256, i % 256)
    )


def points(i: int) -> list[tuple[float, float, float]]:
    """The cloud of message i (float32-exact values)."""
    return [(k + 0.5, float(i), -float(k)) for k in range(POINTS_PER_CLOUD)]


def points_bytes(i: int) -> bytes:
    """`points(i)` packed x, y, z float32 little-endian, 12 bytes a point."""
    return b"".join(struct.pack("<fff", *p) for p in points(i))


def tf_translation(i: int) -> tuple[float, float, float]:
    return (1.0 + i, 2.0, 3.0)


def imu_angular_velocity(i: int) -> tuple[float, float, float]:
    return (0.25, 0.5, 0.125 * i)


IMU_LINEAR_ACCELERATION = (0.0, 0.0, 9.75)
IMU_ORIENTATION = (0.0, 0.0, 0.0, 1.0)  # x, y, z, w


def chatter_text(i: int) -> str:
    return f"hello fleet {i}"


def log_text(i: int) -> str:
    return f"foxglove log line {i}"


def json_status(i: int) -> dict[str, object]:
    return {"battery": 1.0 - i / 8, "mode": "auto" if i % 2 == 0 else "manual", "seq": i}
