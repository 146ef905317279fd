"""A robot for the end-to-end tests: the real Rerun SDK with GrpcSink + FileSink.

python robot.py scene GRPC_URL COPY_PATH RUN_ID   logs half a scene, prints HALF, waits for a
                                                  line on stdin, logs the rest, exits
python robot.py live GRPC_URL COPY_PATH RUN_ID    logs ten frames, prints READY, waits for a line,
                                                  logs ten more, ends its stream
python robot.py many GRPC_URL N                   opens N recordings at once, prints READY,
                                                  waits for a line on stdin, exits
python robot.py token GRPC_URL RUN_ID ROBOT TOKEN  proves itself by its fleet property's token
                                                  ("-": none; ROBOT "-": no robot_id), logs ten
                                                  frames, ends its stream, prints how it ended
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb


def log_frame(rec: rr.RecordingStream, i: int) -> None:
    rec.set_time("frame", sequence=i)
    rec.set_time("sim", duration=i * 0.1)
    rec.log("/world/robot", rr.Transform3D(translation=[i * 0.1, 0.0, 0.0]))
    rec.log("/world/robot/lidar", rr.Points3D(np.random.default_rng(i).random((500, 3), dtype=np.float32)))
    rec.log("/world/robot/camera", rr.Image(np.full((48, 64, 3), i % 255, dtype=np.uint8)))
    rec.log("/robot/battery", rr.Scalars([100.0 - i * 0.5]))
    rec.log("/robot/log", rr.TextLog(f"frame {i}", level=rr.TextLogLevel.INFO))


def scene(url: str, copy: str, run_id: str) -> None:
    rec = rr.RecordingStream("fleet_e2e", recording_id=run_id)
    rec.set_sinks(rr.GrpcSink(url), rr.FileSink(copy))
    rec.send_blueprint(rrb.Blueprint(rrb.Spatial3DView(origin="/world")), make_active=True, make_default=True)
    rec.send_property("fleet", rr.AnyValues(robot_id="robot-e2e", site="lab-3", token="do-not-store"))
    rec.log("/world/map", rr.Points3D([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), static=True)
    for i in range(30):
        log_frame(rec, i)
    rec.flush(timeout_sec=30)
    print("HALF", flush=True)
    sys.stdin.readline()
    for i in range(30, 60):  # the server was killed: the SDK drops these on the floor
        log_frame(rec, i)
    try:
        rec.flush(timeout_sec=5)
    except Exception as exc:  # "gRPC connection severed": expected, the FileSink copy has everything
        print(f"flush: {exc}", file=sys.stderr)
    rec.disconnect()


def live(url: str, copy: str, run_id: str) -> None:
    """Ten frames, READY, wait for a line, ten more frames, then end the stream."""
    rec = rr.RecordingStream("fleet_live", recording_id=run_id)
    rec.set_sinks(rr.GrpcSink(url), rr.FileSink(copy))
    for i in range(10):
        log_frame(rec, i)
    rec.flush(timeout_sec=30)
    print("READY", flush=True)
    sys.stdin.readline()
    for i in range(10, 20):
        log_frame(rec, i)
    rec.flush(timeout_sec=30)
    rec.disconnect()


def many(url: str, n: int) -> None:
    recs = []
    for k in range(n):
        rec = rr.RecordingStream("fleet_many", recording_id=f"many-{k:04d}")
        rec.set_sinks(rr.GrpcSink(url))
        rec.set_time("frame", sequence=0)
        rec.log("/robot/speed", rr.Scalars([float(k)]))
        recs.append(rec)
    for rec in recs:
        rec.flush(timeout_sec=60)
    print("READY", flush=True)
    sys.stdin.readline()
    for rec in recs:
        rec.disconnect()


def with_token(url: str, run_id: str, robot: str, token: str) -> None:
    """What a robot on an auth-on depot does: its token in its fleet property, logged first."""
    rec = rr.RecordingStream("fleet_token", recording_id=run_id)
    rec.set_sinks(rr.GrpcSink(url))
    fleet: dict[str, Any] = {
        **({"robot_id": robot} if robot != "-" else {}),
        **({"token": token} if token != "-" else {}),
    }
    if fleet:
        rec.send_property("fleet", rr.AnyValues(**fleet))
    for i in range(10):
        log_frame(rec, i)
    try:
        rec.flush(timeout_sec=30)
        print("FLUSHED", flush=True)
    except Exception as exc:  # a refused stream: the SDK reports the severed connection
        print(f"FLUSH FAILED: {exc}", flush=True)
    rec.disconnect()


if __name__ == "__main__":
    if sys.argv[1] == "scene":
        scene(sys.argv[2], sys.argv[3], sys.argv[4])
    elif sys.argv[1] == "live":
        live(sys.argv[2], sys.argv[3], sys.argv[4])
    elif sys.argv[1] == "token":
        with_token(*sys.argv[2:6])
    else:
        many(sys.argv[2], int(sys.argv[3]))
