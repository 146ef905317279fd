"""A robot's scene for the corpus tests, logged with the real rerun-sdk, and what rules must find
in it, computed here from the values logged (not by the depot's evaluator).

`python scene.py OUT RUN_ID [TAGS] [calm]` writes the recording (`OUT` a .rrd path, or `grpc:URL`
to stream it, printing READY halfway and waiting for a line on stdin before the rest; FLEET_TOKEN:
the robot's ingest token, sent in its `fleet` property). `calm`: a second, shorter run of another
software version on which the robot stays engaged (CALM_FRAMES, no drops).
"""

from __future__ import annotations

import math
import os
import sys
from typing import Any

FRAMES = 60
T0_S = 1_700_000_000  # sim_time of frame 0, seconds since the epoch
DROPS = ((10, 15), (25, 30), (40, 45))  # /autonomy/engaged is 0 on these frames (end exclusive)
STUCK_FRAMES = (7, 33)  # ERROR logs matching "stuck"
BRAKE_FRAME = 22  # a robot event under /events/hard_brake
SW_VERSION = "2.3.1"
HALF = FRAMES // 2  # a streamed scene waits after these frames
CALM_FRAMES = 20
CALM_SW_VERSION = "2.4.0"
Drops = tuple[tuple[int, int], ...]


def ns(frame: int) -> int:
    return (T0_S + frame) * 1_000_000_000


def engaged(frame: int, drops: Drops = DROPS) -> float:
    return 0.0 if any(a <= frame < b for a, b in drops) else 1.0


def position(frame: int) -> tuple[float, float, float]:
    return (frame * 0.3, (frame % 2) * 0.4, 0.0)


def temperature(frame: int) -> float:
    return 20.0 + frame * 0.1


# --- what the rules must find, from the values above ---------------------------------------------

RULES_V1 = """
[[event]]
name = "intervention"
entity = "/autonomy/engaged"
when = "falls_below"
threshold = 0.5
timeline = "sim_time"
severity = "warn"

[[event]]
name = "stuck"
entity = "/logs/**"
when = "text"
level = "ERROR"
match = "(?i)stuck|blocked"
timeline = "sim_time"
severity = "error"

[[metric]]
name = "distance_m"
kind = "path_length"
entity = "/world/robot"

[[metric]]
name = "interventions"
kind = "event_count"
event = "intervention"

[[metric]]
name = "temp_mean"
kind = "mean"
entity = "/sensors/ambient_temp"

[[metric]]
name = "sw_version"
kind = "property"
property = "fleet.sw_version"
"""

RULES_V2 = """
[[event]]
name = "intervention"
entity = "/autonomy/engaged"
when = "below"
threshold = 0.5
timeline = "sim_time"
severity = "error"

[[metric]]
name = "temp_max"
kind = "max"
entity = "/sensors/ambient_temp"
"""

NAMED = ("/autonomy/engaged", "/logs/nav", "/world/robot", "/sensors/ambient_temp", "/events/hard_brake")


def expected_interventions(frames: int = FRAMES, drops: Drops = DROPS) -> list[tuple[int, int]]:
    """falls_below 0.5: from the first sample under it after one at or over it, to the first sample
    at or over it again (one still under way after the last frame is not complete yet)."""
    found, start = [], None
    for frame in range(frames):
        value, before = engaged(frame, drops), engaged(frame - 1, drops) if frame else None
        if start is None and value < 0.5 and before is not None and before >= 0.5:
            start = frame
        elif start is not None and value >= 0.5:
            found.append((ns(start), ns(frame)))
            start = None
    return found


def expected_distance(frames: int = FRAMES) -> float:
    return sum(math.dist(position(i), position(i + 1)) for i in range(frames - 1))


def expected_temp_mean(frames: int = FRAMES) -> float:
    return sum(temperature(i) for i in range(frames)) / frames


def expected_temp_max(frames: int = FRAMES) -> float:
    return max(temperature(i) for i in range(frames))


def expected_stuck(frames: int = FRAMES) -> list[int]:
    return [ns(f) for f in STUCK_FRAMES if f < frames]


# --- logging it ------------------------------------------------------------------------------------


def log_frame(rec: object, frame: int, drops: Drops = DROPS) -> None:
    import numpy as np
    import rerun as rr

    rec.set_time("sim_time", timestamp=T0_S + frame)  # type: ignore[attr-defined]
    rec.set_time("frame", sequence=frame)  # type: ignore[attr-defined]
    log = rec.log  # type: ignore[attr-defined]
    log("/autonomy/engaged", rr.Scalars(engaged(frame, drops)))
    log("/world/robot", rr.Transform3D(translation=position(frame)))
    log("/sensors/ambient_temp", rr.Scalars(temperature(frame)))
    log("/world/cloud", rr.Points3D(np.random.default_rng(frame).random((4000, 3), dtype=np.float32)))
    if frame in STUCK_FRAMES:
        log("/logs/nav", rr.TextLog("robot stuck at dock 2", level=rr.TextLogLevel.ERROR))
    if frame == 20:
        log("/logs/nav", rr.TextLog("stuck for a moment", level=rr.TextLogLevel.WARN))  # below ERROR
    if frame == 50:
        log("/logs/nav", rr.TextLog("all fine", level=rr.TextLogLevel.ERROR))  # no match
    if frame == BRAKE_FRAME:
        log("/events/hard_brake", rr.TextLog("brake!", level=rr.TextLogLevel.WARN))


def main(out: str, run_id: str, tags: str, calm: bool = False) -> None:
    import rerun as rr

    frames, drops = (CALM_FRAMES, ()) if calm else (FRAMES, DROPS)

    rec = rr.RecordingStream("corpus_scene", recording_id=run_id)
    if out.startswith("grpc:"):
        rec.set_sinks(rr.GrpcSink(out.removeprefix("grpc:")))
    else:
        rec.set_sinks(rr.FileSink(out))
    fields: dict[str, Any] = {
        "robot_id": "robot-c",
        "sw_version": CALM_SW_VERSION if calm else SW_VERSION,
        "tags": tags,
    }
    if os.environ.get("FLEET_TOKEN"):
        fields["token"] = os.environ["FLEET_TOKEN"]  # proves the robot
    rec.send_property("fleet", rr.AnyValues(**fields))
    for frame in range(frames // 2):
        log_frame(rec, frame, drops)
    rec.flush(timeout_sec=30)
    if out.startswith("grpc:"):
        print("READY", flush=True)
        sys.stdin.readline()
    for frame in range(frames // 2, frames):
        log_frame(rec, frame, drops)
    rec.flush(timeout_sec=30)
    rec.disconnect()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "night-shift, dock-2", "calm" in sys.argv[4:])
