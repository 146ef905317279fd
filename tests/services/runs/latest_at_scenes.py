"""Recordings for latest-at tests, written by the real rerun-sdk, and Rerun's own latest-at as the oracle.

`python latest_at_scenes.py CHUNKING OUT.rrd` logs the same scene with a given chunking, in a subprocess
so the SDK's global state never leaks into the test process:

- `/cam`: a 4x4 image at frames 0, 10 .. 90, each filled with its frame number; frame 90 is logged twice
  (90 then 190: same time, the later row wins);
- `/robot`: points at frames 0, 10 .. 90, colors only at frames 0 and 20 (a sparse component);
- `/late`: points at frames 0 .. 90, logged out of order (frame 90 before frame 80: time wins, not row order);
- `/straddle`: one chunk (`send_columns`) with rows at frames 50 and 120, so for a window starting after 50
  its only earlier row sits in a chunk that straddles the start.

Chunkings: `per_call` flushes after every log call (one chunk per call), `batched` lets the SDK's
batcher cut chunks of three rows, `compacted` is `per_call` compacted by `rerun rrd optimize` into chunks
of four rows (sparse components: nulls inside chunks).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

CHUNKINGS = ("per_call", "batched", "compacted")
RECORDING_IDS = {"per_call": "1a7e57a1" * 4, "batched": "1a7e57a2" * 4}
FRAMES = tuple(range(0, 100, 10))


def log_scene(chunking: str, out: Path, rerun_bin: str, timeout: float = 120) -> Path:
    if chunking == "compacted":
        logged = log_scene("per_call", out.with_name(out.stem + "-logged.rrd"), rerun_bin, timeout)
        subprocess.run(
            [rerun_bin, "rrd", "optimize", "--max-rows", "4", str(logged), "-o", str(out)],
            check=True,
            capture_output=True,
            timeout=timeout,
        )
        return out
    env = (
        {**os.environ, "RERUN_FLUSH_NUM_ROWS": "3", "RERUN_FLUSH_TICK_SECS": "1000"}
        if chunking == "batched"
        else dict(os.environ)
    )
    subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), chunking, str(out)],
        check=True,
        timeout=timeout,
        env=env,
        capture_output=True,
    )
    return out


def latest_at(path: Path, times: list[int], timeline: str = "frame") -> dict[str, list[Any]]:
    """Rerun's own answer: per entity/component column, the value the viewer shows at each of `times`
    (latest-at, filled from earlier rows), read with the SDK's chunk store and DataFusion."""
    import rerun as rr

    store = rr.chunk.RrdReader(path).stream().collect()
    table = store.reader(timeline, fill_latest_at=True, using_index_values=times).to_arrow_table()
    return {
        name: table.column(name).to_pylist()
        for name in table.column_names
        if ":" in name and not name.startswith("/__properties")
    }


def _log(chunking: str, out: str) -> None:
    import numpy as np
    import rerun as rr

    rr.init("fleet-latest-at", recording_id=RECORDING_IDS[chunking], spawn=False)
    rr.save(out)
    recording = rr.get_global_data_recording()
    assert recording is not None

    def flush() -> None:
        if chunking == "per_call":
            recording.flush()

    late_order = [*FRAMES[:-2], 90, 80]
    for step, frame in enumerate(FRAMES):
        rr.set_time("frame", sequence=frame)
        rr.log("/cam", rr.Image(np.full((4, 4), frame, dtype=np.uint8)))
        flush()
        colors = [255, frame, 0] if frame in (0, 20) else None
        rr.log("/robot", rr.Points3D(np.full((2, 3), frame, dtype=np.float32), colors=colors))
        flush()
        rr.set_time("frame", sequence=late_order[step])
        rr.log("/late", rr.Points3D(np.full((1, 3), late_order[step], dtype=np.float32)))
        flush()
    rr.set_time("frame", sequence=90)
    rr.log("/cam", rr.Image(np.full((4, 4), 190, dtype=np.uint8)))
    flush()
    rr.send_columns(
        "/straddle",
        indexes=[rr.TimeColumn("frame", sequence=[50, 120])],
        columns=rr.Points3D.columns(positions=np.array([[50, 50, 50], [120, 120, 120]], dtype=np.float32)).partition(
            [1, 1]
        ),
    )
    recording.flush()


if __name__ == "__main__":
    _log(sys.argv[1], sys.argv[2])
