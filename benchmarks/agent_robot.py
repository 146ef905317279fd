"""A robot for `benchmarks/agent.py`: the real Rerun SDK streaming a typical robot's data at a fixed
rate to a gRPC URL (the agent's, or the depot's), with a FileSink copy beside it.

    python benchmarks/agent_robot.py GRPC_URL COPY_PATH RUN_ID SECONDS RATE_HZ [jpeg|raw] [BRAKE_AT_S]

Each frame: a camera image (jpeg: 50 kB of incompressible bytes as a 640x480 JPEG would be; raw:
320x240 RGB, 230 kB), a lidar sweep of 10,000 points (120 kB), eight scalars (battery, speed, six
joints), a pose and a log line; the SDK's own batching (its defaults) makes the chunks. The data is
drawn ahead of time from a small pool, so the robot's CPU is what logging costs, not making noise.

Protocol on stdin/stdout: prints READY once its sinks are set, waits for a line, streams for
SECONDS, flushes, prints one JSON line (monotonic times `start` and `flushed`, `frames`, `late`:
frames logged over a period behind time, `cpu_s`: this process's CPU while streaming), ends its
stream and prints DONE. With BRAKE_AT_S it also logs `/metrics/brake` each frame, 9.0 in the frame at
that second and 0.5 in the others, and the JSON line gives `brake_wall`: the wall-clock time (seconds
since the epoch) it logged the spike.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import rerun as rr

POOL = 8  # distinct frames of data, cycled
JPEG_BYTES = 50_000
RAW_SHAPE = (240, 320, 3)
LIDAR_POINTS = 10_000
JOINTS = 6


def data_pool(camera: str) -> list[tuple[rr.AsComponents, np.ndarray]]:
    rng = np.random.default_rng(7)
    pool: list[tuple[rr.AsComponents, np.ndarray]] = []
    for _ in range(POOL):
        image: rr.AsComponents
        if camera == "jpeg":
            image = rr.EncodedImage(contents=b"\xff\xd8\xff\xe0" + rng.bytes(JPEG_BYTES - 4), media_type="image/jpeg")
        else:
            image = rr.Image(rng.integers(0, 255, RAW_SHAPE, dtype=np.uint8))
        pool.append((image, rng.random((LIDAR_POINTS, 3), dtype=np.float32) * 40.0 - 20.0))
    return pool


def log_frame(rec: rr.RecordingStream, i: int, rate_hz: float, frame: tuple[rr.AsComponents, np.ndarray]) -> None:
    image, points = frame
    t = i / rate_hz
    rec.set_time("frame", sequence=i)
    rec.set_time("sim", duration=t)
    rec.log("/world/robot", rr.Transform3D(translation=[t * 0.5, np.sin(t), 0.0]))
    rec.log("/world/robot/camera", image)
    rec.log("/world/robot/lidar", rr.Points3D(points))
    rec.log("/metrics/battery", rr.Scalars([100.0 - t * 0.01]))
    rec.log("/metrics/speed", rr.Scalars([0.5 + 0.1 * np.sin(t)]))
    for joint in range(JOINTS):
        rec.log(f"/metrics/joints/j{joint}", rr.Scalars([np.sin(t + joint)]))
    rec.log("/logs/robot", rr.TextLog(f"frame {i}: nominal", level=rr.TextLogLevel.INFO))


def stream(
    url: str, copy: str, run_id: str, seconds: float, rate_hz: float, camera: str, brake_at: float | None = None
) -> None:
    pool = data_pool(camera)
    rec = rr.RecordingStream("fleet_agent_bench", recording_id=run_id)
    rec.set_sinks(rr.GrpcSink(url), rr.FileSink(copy))
    rec.send_property("fleet", rr.AnyValues(robot_id="robot-bench", site="bench"))
    print("READY", flush=True)
    sys.stdin.readline()
    cpu0 = time.process_time()  # every thread of the process, the SDK's included
    start = time.monotonic()
    frames = round(seconds * rate_hz)
    late = 0
    brake_frame = round(brake_at * rate_hz) if brake_at is not None else None
    brake_wall: float | None = None
    for i in range(frames):
        due = start + i / rate_hz
        wait = due - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # the robot's own clock: one frame a period
        elif wait < -1 / rate_hz:
            late += 1
        log_frame(rec, i, rate_hz, pool[i % POOL])
        if brake_frame is not None:
            if i == brake_frame:
                brake_wall = time.time()
            rec.log("/metrics/brake", rr.Scalars([9.0 if i == brake_frame else 0.5]))
    rec.flush(timeout_sec=60)
    flushed = time.monotonic()
    result = {
        "start": start,
        "flushed": flushed,
        "frames": frames,
        "late": late,
        "cpu_s": time.process_time() - cpu0,
        "brake_wall": brake_wall,
    }
    print(json.dumps(result), flush=True)
    rec.disconnect()
    print("DONE", flush=True)


if __name__ == "__main__":
    url, copy, run_id, seconds, rate_hz, *rest = sys.argv[1:]
    brake = float(rest[1]) if len(rest) > 1 else None
    stream(url, copy, run_id, float(seconds), float(rate_hz), rest[0] if rest else "jpeg", brake)
