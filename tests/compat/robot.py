"""A robot on any released rerun-sdk (run with the Python of that SDK's venv).

    python robot.py stream GRPC_URL COPY_PATH RUN_ID   streams a short scene live, keeping a copy
    python robot.py save COPY_PATH RUN_ID              writes the scene to a file only (for upload)

With FLEET_ROBOT and FLEET_TOKEN set, the scene starts with the `fleet` property naming the robot
and carrying its token (how an unmodified SDK stream proves itself to a depot with auth on).

Uses only API every SDK from 0.22 on has, choosing the sinks the SDK offers: `set_sinks`
(GrpcSink + FileSink, 0.25 on), else a gRPC stream plus a second stream saved to the copy.
Every log call is its own chunk (RERUN_FLUSH_NUM_ROWS=1, set by the test), so both copies of a
two-stream robot hold the same chunks.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import rerun as rr

APPLICATION_ID = "fleet_compat"


def log_scene(rec: rr.RecordingStream) -> None:
    if os.environ.get("FLEET_TOKEN"):  # first: a depot with auth on holds the stream until it comes
        fleet = rr.AnyValues(robot_id=os.environ["FLEET_ROBOT"], token=os.environ["FLEET_TOKEN"])
        rec.send_property("fleet", fleet)
    rec.log("/world/map", rr.Points3D([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), static=True)
    for i in range(5):
        rec.set_time("frame", sequence=i)
        # axis_length: a component whose descriptor newer Rerun migrates (Transform3D -> TransformAxes3D),
        # and SDKs that know TransformAxes3D log it there
        if hasattr(rr, "TransformAxes3D"):
            rec.log("/world/robot", rr.Transform3D(translation=[i * 0.1, 0.0, 0.0]), rr.TransformAxes3D(0.5))
        else:
            rec.log("/world/robot", rr.Transform3D(translation=[i * 0.1, 0.0, 0.0], axis_length=0.5))  # type: ignore[call-arg]
        rec.log("/world/robot/lidar", rr.Points3D(np.random.default_rng(i).random((50, 3), dtype=np.float32)))
        rec.log("/robot/battery", rr.Scalars([100.0 - i]))
        rec.log("/robot/log", rr.TextLog(f"frame {i}", level=rr.TextLogLevel.INFO))


def stream(url: str, copy: str, run_id: str) -> None:
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=run_id)
    if hasattr(rec, "set_sinks"):
        rec.set_sinks(rr.GrpcSink(url), rr.FileSink(copy))
        log_scene(rec)
        rec.flush()
        rec.disconnect()
        return
    twin = rr.RecordingStream(APPLICATION_ID, recording_id=run_id)
    rec.connect_grpc(url)
    twin.save(copy)
    both = Both(rec, twin)
    log_scene(both)  # type: ignore[arg-type]
    for r in (rec, twin):
        r.flush()
        r.disconnect()


class Both:
    """The same calls on two recording streams (SDKs without set_sinks have one sink each)."""

    def __init__(self, *recs: rr.RecordingStream) -> None:
        self.recs = recs

    def __getattr__(self, name: str):
        def call(*args, **kwargs):
            for rec in self.recs:
                getattr(rec, name)(*args, **kwargs)

        return call


def save(copy: str, run_id: str) -> None:
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=run_id)
    rec.save(copy)
    log_scene(rec)
    rec.flush()
    rec.disconnect()


if __name__ == "__main__":
    if sys.argv[1] == "stream":
        stream(*sys.argv[2:5])
    else:
        save(*sys.argv[2:4])
