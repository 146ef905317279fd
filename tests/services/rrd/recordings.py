"""Real Rerun recordings for the codec tests, written by the real rerun-sdk.

Each scene runs in its own Python subprocess (`python recordings.py SCENE OUT_DIR`) so the SDK's
global state never leaks between scenes or into the test process. Besides `SCENE.rrd` every scene
writes `SCENE.json`, the ground truth of what it logged:

    {"scene": ..., "footer": bool,
     "recordings": [{"application_id", "recording_id", "blueprint": bool,
                     "log_time": [lo_ns, hi_ns],          # wall clock around the logging calls
                     "properties": {name: {field: value}},
                     "entities": {path: {"static_rows", "temporal_rows", "archetypes", "components",
                                         "timelines": {name: {"type", "min", "max"}},
                                         "component_rows": {component: rows}, "sdk": bool}}}]}

Timelines are set with exact integers (numpy ns values), so min/max are known to the nanosecond.
`log_time` is added by the SDK to every temporal row; only its bounds are known.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Scenes that each produce one .rrd file with one recording (two for "merged" inputs).
SCENES = (
    "points",
    "image",
    "scalars",
    "textlogs",
    "transforms",
    "static",
    "properties",
    "blueprint",
    "no_footer",
    "merge_a",
    "merge_b",
    "large",
)

# Files written by the SDK in one piece (two SetStoreInfo per store, as the SDK always sends): every scene.
SDK_FILES = SCENES
# Re-encoded by the rerun CLI (one SetStoreInfo per store).
CLI_FILES = ("merged", "optimized")
# Everything that decodes without error.
WHOLE_FILES = (*SDK_FILES, *CLI_FILES)
FOOTER_FILES = tuple(name for name in WHOLE_FILES if name != "no_footer")

BASE_TS = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z in ns


@dataclass(frozen=True)
class Recording:
    """A generated file and its ground truth."""

    name: str
    path: Path
    truth: dict[str, Any]

    @property
    def data(self) -> bytes:
        return self.path.read_bytes()

    @property
    def recordings(self) -> list[dict[str, Any]]:
        return list(self.truth["recordings"])


# --- run in the test process -----------------------------------------------------------------


@dataclass(frozen=True)
class Frame:
    """One message frame: its 16-byte header at `offset`, then `length` bytes of protobuf."""

    offset: int
    kind: int
    length: int

    @property
    def payload_offset(self) -> int:
        return self.offset + 16

    @property
    def end(self) -> int:
        return self.offset + 16 + self.length


def walk_frames(data: bytes) -> tuple[list[Frame], int | None]:
    """The frames of one whole RRD stream read with plain `struct` (independent of services.rrd),
    and the offset of the stream footer after End (None when there is none)."""
    assert data[:4] == b"RRF2", data[:4]
    pos, frames = 12, []
    while pos < len(data):
        kind, length = struct.unpack_from("<QQ", data, pos)
        assert kind <= 3 and pos + 16 + length <= len(data), (pos, kind, length)
        frames.append(Frame(pos, kind, length))
        pos += 16 + length
        if kind == 0:
            break
    trailer = pos if pos < len(data) else None
    return frames, trailer


def start_scene(scene: str, out_dir: Path) -> subprocess.Popen[bytes]:
    """A scene's recording, its chunks cut only where it flushes or by size: the SDK's batcher also
    flushes on a timer (every few ms), which on a loaded machine fires mid-scene and adds a chunk."""
    return subprocess.Popen(
        [sys.executable, str(Path(__file__).resolve()), scene, str(out_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "RERUN_FLUSH_TICK_SECS": "3600"},
    )


def generate_scenes(scenes: tuple[str, ...], out_dir: Path, timeout: float = 120) -> dict[str, Recording]:
    """Run every scene in its own subprocess (in parallel) and load the results."""
    procs = {scene: start_scene(scene, out_dir) for scene in scenes}
    failures = []
    for scene, proc in procs.items():
        _, err = proc.communicate(timeout=timeout)
        if proc.returncode != 0:
            failures.append(f"{scene}: exit {proc.returncode}\n{err.decode(errors='replace')}")
    if failures:
        raise RuntimeError("recording generation failed:\n" + "\n".join(failures))
    return {scene: load(scene, out_dir) for scene in scenes}


def load(scene: str, out_dir: Path) -> Recording:
    truth = json.loads((out_dir / f"{scene}.json").read_text())
    return Recording(scene, out_dir / f"{scene}.rrd", truth)


def rerun_rrd_ok(rerun_bin: str, *args: str | Path, timeout: float = 120) -> str:
    """`rerun rrd ARGS...` (compare, verify, ...) succeeds, or the test fails with what it said;
    what it printed."""
    done = subprocess.run([rerun_bin, "rrd", *map(str, args)], capture_output=True, text=True, timeout=timeout)
    said = done.stdout + done.stderr
    assert done.returncode == 0, f"rerun rrd {' '.join(map(str, args))}: {said[-4000:]}"
    return said


def rerun_rrd(rerun_bin: str, command: str, inputs: list[Recording], out_dir: Path, name: str) -> Recording:
    """`rerun rrd merge|optimize IN... -o OUT`: one stream (with footer) holding every input recording,
    re-encoded by Rerun (`optimize` also compacts chunks of an entity into one)."""
    out = out_dir / f"{name}.rrd"
    subprocess.run(
        [rerun_bin, "rrd", command, *(str(r.path) for r in inputs), "-o", str(out)],
        check=True,
        capture_output=True,
        timeout=120,
    )
    truth = {"scene": name, "footer": True, "recordings": [rec for r in inputs for rec in r.recordings]}
    (out_dir / f"{name}.json").write_text(json.dumps(truth, indent=1))
    return Recording(name, out, truth)


def cut_mid_arrow(source: Recording, out_dir: Path, name: str, index: int) -> Recording:
    """A copy of `source` cut in the middle of the payload of its `index`-th ArrowMsg (a crash
    mid-write). The truth gains `cut_at` (the file size) and `cut_message_offset` (the offset of
    the torn message's header)."""
    frames, _ = walk_frames(source.data)
    torn = [f for f in frames if f.kind == 2][index]
    at = torn.payload_offset + torn.length // 2
    out = out_dir / f"{name}.rrd"
    out.write_bytes(source.data[:at])
    truth = {**source.truth, "scene": name, "footer": False, "cut_at": at, "cut_message_offset": torn.offset}
    (out_dir / f"{name}.json").write_text(json.dumps(truth, indent=1))
    return Recording(name, out, truth)


# --- run in the scene subprocess -------------------------------------------------------------


class Truth:
    """Logs through a RecordingStream and records what was logged."""

    def __init__(self, rr: Any, application_id: str, recording_id: str) -> None:
        self.rr = rr
        self.t_start = time.time_ns()
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
        self.times: dict[str, tuple[str, int]] = {}
        self.truth: dict[str, Any] = {
            "application_id": application_id,
            "recording_id": recording_id,
            "blueprint": False,
            "properties": {},
            "entities": {},
        }
        # send_properties=True (the default): the SDK logs RecordingInfo:start_time itself.
        self.entities["/__properties"] = {
            "static_rows": 1,
            "temporal_rows": 0,
            "archetypes": ["rerun.archetypes.RecordingInfo"],
            "components": ["RecordingInfo:start_time"],
            "component_rows": {"RecordingInfo:start_time": 1},
            "timelines": {},
            "sdk": True,
        }

    @property
    def entities(self) -> dict[str, Any]:
        return self.truth["entities"]  # type: ignore[no-any-return]

    def set_time(
        self, timeline: str, *, sequence: int | None = None, duration: int | None = None, timestamp: int | None = None
    ) -> None:
        import numpy as np

        if sequence is not None:
            self.rec.set_time(timeline, sequence=sequence)
            self.times[timeline] = ("sequence", sequence)
        elif duration is not None:
            self.rec.set_time(timeline, duration=np.timedelta64(duration, "ns"))
            self.times[timeline] = ("duration", duration)
        else:
            assert timestamp is not None
            self.rec.set_time(timeline, timestamp=np.datetime64(timestamp, "ns"))
            self.times[timeline] = ("timestamp", timestamp)

    def disable_timeline(self, timeline: str) -> None:
        self.rec.disable_timeline(timeline)
        del self.times[timeline]

    def _record(self, path: str, archetype: Any, static: bool) -> None:
        entity = self.entities.setdefault(
            path,
            {
                "static_rows": 0,
                "temporal_rows": 0,
                "archetypes": [],
                "components": [],
                "component_rows": {},
                "timelines": {},
                "sdk": False,
            },
        )
        for batch in archetype.as_component_batches():
            descr = batch.component_descriptor()
            if descr.archetype and descr.archetype not in entity["archetypes"]:
                entity["archetypes"].append(descr.archetype)
            if descr.component not in entity["components"]:
                entity["components"].append(descr.component)
            entity["component_rows"][descr.component] = entity["component_rows"].get(descr.component, 0) + 1
        if static:
            entity["static_rows"] += 1
            return
        entity["temporal_rows"] += 1
        for name, (kind, value) in self.times.items():
            tl = entity["timelines"].setdefault(name, {"type": kind, "min": value, "max": value})
            tl["min"], tl["max"] = min(tl["min"], value), max(tl["max"], value)

    def log(self, path: str, archetype: Any, *, static: bool = False) -> None:
        self.rec.log(path, archetype, static=static)
        self._record(path, archetype, static)

    def send_property(self, name: str, values: dict[str, Any]) -> None:
        archetype = self.rr.AnyValues(**values)
        self.rec.send_property(name, archetype)
        self._record(f"/__properties/{name}", archetype, static=True)
        self.truth["properties"][name] = values

    def close(self) -> dict[str, Any]:
        self.rec.flush()
        self.rec.disconnect()
        self.truth["log_time"] = [self.t_start, time.time_ns()]
        return self.truth


def _scene_points(rr: Any, out: Path) -> list[Truth]:
    import numpy as np

    t = Truth(rr, "fleet_points", "rec-points")
    t.rec.save(out)
    for i in range(6):
        t.set_time("frame", sequence=100 + i)
        t.set_time("sim", duration=250_000_000 * i)
        positions = np.arange(30, dtype=np.float32).reshape(10, 3) + i
        if i % 3 == 1:  # no colors in this row: a null cell in the chunk's colors column
            t.log("/world/points", rr.Points3D(positions, radii=0.1 * (i + 1)))
        else:
            t.log("/world/points", rr.Points3D(positions, radii=0.1 * (i + 1), colors=[255, 0, i]))
        if i % 2 == 0:
            t.log("/world/sparse", rr.Points2D([[i, i]]))
        if i == 2:
            t.rec.flush()  # the batcher starts new chunks: rows of one entity over several chunks
    return [t]


def _scene_image(rr: Any, out: Path) -> list[Truth]:
    import numpy as np

    t = Truth(rr, "fleet_camera", "rec-image")
    t.rec.save(out)
    for i in range(3):
        t.set_time("frame", sequence=i)
        t.set_time("capture", timestamp=BASE_TS + 33_333_333 * i)
        t.log("/camera/rgb", rr.Image(np.full((4, 6, 3), i, dtype=np.uint8)))
        t.log("/camera/gray", rr.Image(np.arange(24, dtype=np.uint8).reshape(4, 6) + i))
    return [t]


def _scene_large(rr: Any, out: Path) -> list[Truth]:
    """Chunks of about 1 MB (random, so LZ4 cannot shrink them): the decoder's large-message path."""
    import numpy as np

    rng = np.random.default_rng(7)
    t = Truth(rr, "fleet_large", "rec-large")
    t.rec.save(out)
    for i in range(3):
        t.set_time("frame", sequence=i)
        t.log("/camera/rgb", rr.Image(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)))
        t.log("/lidar", rr.Points3D(rng.random((30_000, 3), dtype=np.float32)))
    return [t]


def _scene_scalars(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_scalars", "rec-scalars")
    t.rec.save(out)
    steps = [5, 1, 9, 3, 7, -4, 12, 0]  # out of order on purpose: chunks are not sorted
    for n, step in enumerate(steps):
        t.set_time("step", sequence=step)
        t.set_time("wall", timestamp=BASE_TS + 1_000_000 * step + 7)
        t.log("/robot/speed", rr.Scalars([float(step)]))
        t.log("/robot/battery", rr.Scalars([0.5, 0.25 * n]))
        if n == 3:
            t.rec.flush()
    return [t]


def _scene_textlogs(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_logs", "rec-textlogs")
    t.rec.save(out)
    levels = [
        rr.TextLogLevel.INFO,
        rr.TextLogLevel.WARN,
        rr.TextLogLevel.ERROR,
        rr.TextLogLevel.DEBUG,
        rr.TextLogLevel.CRITICAL,
    ]
    for i, level in enumerate(levels):
        t.set_time("uptime", duration=1_500_000_000 * i + 123)
        t.log("/logs/robot", rr.TextLog(f"event {i}", level=level))
    t.log("/logs/plain", rr.TextLog("no level"))
    return [t]


def _scene_transforms(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_tf", "rec-transforms")
    t.rec.save(out)
    for i in range(4):
        t.set_time("frame", sequence=i * 10)
        t.set_time("wall", timestamp=BASE_TS + 10**9 * i)
        t.log("/world/robot", rr.Transform3D(translation=[i, 0.0, 0.0]))
        t.log(
            "/world/robot/arm",
            rr.Transform3D(translation=[0.0, 0.0, 1.0], quaternion=rr.Quaternion(xyzw=[0.0, 0.0, 0.0, 1.0])),
        )
    return [t]


def _scene_static(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_static", "rec-static")
    t.rec.save(out)
    t.log("/world/origin", rr.Points3D([[0.0, 0.0, 0.0]], radii=0.5), static=True)
    t.log("/world/label", rr.TextLog("first"), static=True)
    t.log("/world/label", rr.TextLog("second"), static=True)
    t.log("/world/mixed", rr.TextLog("static part"), static=True)
    for i in range(3):
        t.set_time("frame", sequence=i)
        t.log("/world/mixed", rr.TextLog(f"tick {i}"))
    return [t]


def _scene_properties(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_props", "rec-properties")
    t.rec.save(out)
    t.send_property("fleet", {"robot_id": "robot-7", "token": "s3cr3t-token"})
    t.send_property("vehicle", {"vin": "VIN0123456789", "model": "crawler"})
    for i in range(2):
        t.set_time("frame", sequence=i)
        t.log("/robot/speed", rr.Scalars([1.0 + i]))
    return [t]


def _scene_blueprint(rr: Any, out: Path) -> list[Truth]:
    import rerun.blueprint as rrb

    t = Truth(rr, "fleet_bp", "rec-blueprint")
    t.rec.save(
        out,
        default_blueprint=rrb.Blueprint(
            rrb.Horizontal(rrb.Spatial3DView(origin="/world"), rrb.TimeSeriesView(origin="/robot")),
            collapse_panels=True,
        ),
    )
    t.truth["blueprint"] = True
    for i in range(3):
        t.set_time("frame", sequence=i)
        t.log("/world/points", rr.Points3D([[i, 0.0, 0.0]]))
        t.log("/robot/speed", rr.Scalars([float(i)]))
    return [t]


def _scene_no_footer(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_nofooter", "rec-no-footer")
    t.rec.set_sinks(rr.FileSink(str(out), write_footer=False))
    for i in range(4):
        t.set_time("frame", sequence=i)
        t.log("/robot/speed", rr.Scalars([float(i)]))
        t.log("/logs", rr.TextLog(f"line {i}", level=rr.TextLogLevel.INFO))
    return [t]


def _scene_merge_a(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_merge", "rec-merge-a")
    t.rec.save(out)
    for i in range(3):
        t.set_time("frame", sequence=i)
        t.log("/robot/speed", rr.Scalars([float(i)]))
    return [t]


def _scene_merge_b(rr: Any, out: Path) -> list[Truth]:
    t = Truth(rr, "fleet_merge", "rec-merge-b")
    t.rec.save(out)
    for i in range(2):
        t.set_time("tick", duration=10**9 * i)
        t.log("/world/points", rr.Points3D([[0.0, i, 0.0]]))
    return [t]


def run_scene(scene: str, out_dir: Path) -> None:
    import rerun as rr

    scene_fn = globals()[f"_scene_{scene}"]
    out = out_dir / f"{scene}.rrd"
    truths = scene_fn(rr, out)
    truth = {
        "scene": scene,
        "footer": scene != "no_footer",
        "recordings": [t.close() for t in truths],
    }
    (out_dir / f"{scene}.json").write_text(json.dumps(truth, indent=1))


if __name__ == "__main__":
    run_scene(sys.argv[1], Path(sys.argv[2]))
