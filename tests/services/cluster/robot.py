"""A robot streaming straight to a depot node: the real Rerun SDK with a GrpcSink to the node and a
FileSink copy, proving itself with the ingest token in its fleet property (read from FLEET_TOKEN,
so it is on no command line). Its frames are those of the agent suite's robot.

python robot.py GRPC_URL COPY_PATH RUN_ID ROBOT STEPS FRAMES   logs FRAMES frames per step; after each
    step prints STEP k and waits for a line on stdin; after the last, ends its stream, prints DONE.
    A stream that broke (its node was killed) is reported on stderr; the FileSink copy goes on.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import rerun as rr

_spec = importlib.util.spec_from_file_location("agent_robot", Path(__file__).parents[1] / "agent" / "robot.py")
assert _spec is not None and _spec.loader is not None
agent_robot = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(agent_robot)  # sets RERUN_FLUSH_NUM_ROWS before the SDK batches anything


def steps(url: str, copy: str, run_id: str, robot: str, count: int, frames: int) -> None:
    rec = rr.RecordingStream("fleet_cluster_e2e", recording_id=run_id)
    rec.set_sinks(rr.GrpcSink(url), rr.FileSink(copy))
    rec.send_property("fleet", rr.AnyValues(robot_id=robot, token=os.environ["FLEET_TOKEN"]))
    rec.log("/world/map", rr.Points3D([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), static=True)
    for step in range(count):
        for i in range(step * frames, (step + 1) * frames):
            agent_robot.log_frame(rec, i)
        agent_robot.flush(rec)
        print(f"STEP {step + 1}", flush=True)
        sys.stdin.readline()
    agent_robot.flush(rec)
    rec.disconnect()
    print("DONE", flush=True)


if __name__ == "__main__":
    url, copy, run_id, robot, count, frames = sys.argv[1:7]
    steps(url, copy, run_id, robot, int(count), int(frames))
