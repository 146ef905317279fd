"""A robot for the agent's end-to-end tests: the real Rerun SDK streaming to its local agent, with
a FileSink copy (the robot's own file, what the depot's run must equal in the end).

python robot.py steps GRPC_URL COPY_PATH RUN_ID STEPS FRAMES   logs FRAMES frames per step; after each
    step prints STEP k and waits for a line on stdin; after the last, ends its stream, prints DONE
python robot.py file COPY_PATH RUN_ID FRAMES                   only a FileSink: logs FRAMES frames, prints
    DONE (the agent watches the folder)
(GRPC_URL "-": no GrpcSink.)
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("RERUN_FLUSH_NUM_ROWS", "1")  # a chunk per entity and frame, as a robot logging at rate
import numpy as np
import rerun as rr


def log_frame(rec: rr.RecordingStream, i: int) -> None:
    """About 60 kB a frame: a camera image, a lidar sweep, a scalar and a log line."""
    rec.set_time("frame", sequence=i)
    rec.set_time("sim", duration=i * 0.1)
    rec.log("/world/robot", rr.Transform3D(translation=[i * 0.1, 0.0, 0.0]))
    rec.log("/world/robot/lidar", rr.Points3D(np.random.default_rng(i).random((400, 3), dtype=np.float32)))
    noise = np.random.default_rng(1000 + i).integers(0, 255, (96, 160, 3), dtype=np.uint8)  # as a camera: no LZ4 gain
    rec.log("/world/robot/camera", rr.Image(noise))
    rec.log("/metrics/battery", rr.Scalars([100.0 - i * 0.1]))
    rec.log("/logs/robot", rr.TextLog(f"frame {i}", level=rr.TextLogLevel.INFO))


def recording(run_id: str, url: str, copy: str) -> rr.RecordingStream:
    rec = rr.RecordingStream("fleet_agent_e2e", recording_id=run_id)
    sinks = [rr.FileSink(copy)] if url == "-" else [rr.GrpcSink(url), rr.FileSink(copy)]
    rec.set_sinks(*sinks)
    rec.send_property("fleet", rr.AnyValues(robot_id="robot-agent", site="lab-7"))
    rec.log("/world/map", rr.Points3D([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), static=True)
    return rec


def flush(rec: rr.RecordingStream) -> None:
    try:
        rec.flush(timeout_sec=30)
    except Exception as exc:  # the agent was killed: its stream is gone, the FileSink has everything
        print(f"flush: {exc}", file=sys.stderr)


def steps(url: str, copy: str, run_id: str, count: int, frames: int) -> None:
    rec = recording(run_id, url, copy)
    for step in range(count):
        for i in range(step * frames, (step + 1) * frames):
            log_frame(rec, i)
        flush(rec)
        print(f"STEP {step + 1}", flush=True)
        sys.stdin.readline()
    flush(rec)
    rec.disconnect()
    print("DONE", flush=True)


def file_only(copy: str, run_id: str, frames: int) -> None:
    rec = recording(run_id, "-", copy)
    for i in range(frames):
        log_frame(rec, i)
    rec.flush(timeout_sec=30)
    rec.disconnect()
    print("DONE", flush=True)


if __name__ == "__main__":
    mode, *args = sys.argv[1:]
    if mode == "steps":
        steps(args[0], args[1], args[2], int(args[3]), int(args[4]))
    elif mode == "file":
        file_only(args[0], args[1], int(args[2]))
    else:
        raise SystemExit(f"unknown mode {mode}")
