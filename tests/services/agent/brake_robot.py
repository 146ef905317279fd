"""A robot for the trigger tests: the real Rerun SDK streaming to its local agent (and a FileSink copy)
a drive at 10 Hz on a `sim_time` timestamp timeline (so minutes of data log in seconds): a camera, a
lidar and a brake pressure that spikes at the given frames.

python brake_robot.py GRPC_URL COPY_PATH RUN_ID FRAMES BRAKES PAUSES
    BRAKES: frames where the brake spikes (comma-separated); PAUSES: frames before which it prints
    `AT FRAME` and waits for a line on stdin. At the end it prints DONE.
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("RERUN_FLUSH_NUM_ROWS", "1")  # a chunk per entity and frame, as a robot logging at rate
import numpy as np
import rerun as rr

START_NS = 1_790_000_000_000_000_000  # 2026-09-21: the drive's first frame
FRAME_NS = 100_000_000  # 10 Hz


def frame(rec: rr.RecordingStream, i: int, braking: bool) -> None:
    rec.set_time("sim_time", timestamp=np.datetime64(START_NS + i * FRAME_NS, "ns"))
    rec.log("/camera/front", rr.Image(np.random.default_rng(i).integers(0, 255, (24, 32, 3), dtype=np.uint8)))
    rec.log("/lidar/top", rr.Points3D(np.random.default_rng(10_000 + i).random((64, 3), dtype=np.float32)))
    rec.log("/metrics/brake", rr.Scalars([9.0 if braking else 0.5]))


def main(url: str, copy: str, run_id: str, frames: int, brakes: set[int], pauses: set[int]) -> None:
    rec = rr.RecordingStream("fleet_trigger_e2e", recording_id=run_id)
    rec.set_sinks(rr.GrpcSink(url), rr.FileSink(copy))
    rec.send_property("fleet", rr.AnyValues(robot_id="robot-agent", site="lab-7"))
    for i in range(frames):
        if i in pauses:
            rec.flush(timeout_sec=30)
            print(f"AT {i}", flush=True)
            sys.stdin.readline()
        frame(rec, i, i in brakes)
    rec.flush(timeout_sec=30)
    rec.disconnect()
    print("DONE", flush=True)


def frames_of(text: str) -> set[int]:
    return {int(part) for part in text.split(",") if part}


if __name__ == "__main__":
    url, copy, run_id, frames, brakes, pauses = sys.argv[1:]
    main(url, copy, run_id, int(frames), frames_of(brakes), frames_of(pauses))
