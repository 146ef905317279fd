"""Latest-at in slices equals latest-at over every row at once, whatever the chunks' order and overlap
(rows logged out of time order, chunks that overlap, rows at one time twice), and holds only the
rows it still needs between slices. Recordings logged with the real rerun-sdk, read back from an RRD
file as the command line's export reads a downloaded episode."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from services.datasets import grid
from services.datasets.local import open_rrd_file
from services.datasets.quality import EpisodeQuality, Limits
from services.datasets.samples import read_series

S = 1_000_000_000
START = 1_790_000_000 * S
ENTITIES = ("/a", "/b", "/c")


def logged(path: Path, seed: int) -> dict[str, list[tuple[int, float]]]:
    """Rows logged in shuffled batches (each flushed as chunks of its own); what was logged."""
    rng = random.Random(seed)
    rows = [(entity, START + rng.randrange(0, 20 * S, S // 20)) for entity in ENTITIES for _ in range(60)]
    rng.shuffle(rows)
    rec = rr.RecordingStream("grid_test", recording_id=f"grid-{seed}")
    rec.save(str(path))
    held: dict[str, list[tuple[int, float]]] = {e: [] for e in ENTITIES}
    for i, (entity, at) in enumerate(rows):
        value = float(i)
        rec.set_time("t", timestamp=np.datetime64(at, "ns"))
        rec.log(entity, rr.Scalars([value]))
        held[entity].append((at, value))
        if rng.random() < 0.1:
            rec.flush()
    rec.flush()
    rec.disconnect()
    return held


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_slices_give_the_latest_at_of_all_rows(tmp_path: Path, seed: int):
    logged(tmp_path / "r.rrd", seed)
    recording = open_rrd_file(tmp_path / "r.rrd")
    try:
        rows = grid.timed_rows(list(recording.index()), "t", lambda p: p in ENTITIES)
        assert len(rows) > 5  # several chunks, overlapping in time
        whole = read_series(grid.reader(recording)(rows), "t", set(ENTITIES))
        times = grid.grid_times(START - S, START + 21 * S, 7)
        quality = EpisodeQuality(Limits())
        sampler = grid.GridSampler(rows, "t", grid.reader(recording), quality)
        held_most = 0
        seen = 0
        for part in sampler.slices(times, frames=5):
            for entity in ENTITIES:
                expected = whole[entity].at(part.grid)
                got = part.picks[entity]
                assert (got >= 0).tolist() == (expected >= 0).tolist()
                series = whole[entity]
                for g, e in zip(got.tolist(), expected.tolist(), strict=True):
                    if e >= 0:  # the latest row at or before the grid time (of rows at one time, any)
                        same_time = [
                            v[0] for t, v in zip(series.times, series.values, strict=True) if t == series.times[e]
                        ]
                        assert float(part.values[entity][g][0]) in same_time
            held_most = max(held_most, sum(len(s.series.times) for s in sampler._seen.values()))
            seen += len(part.grid)
        assert seen == len(times)
        assert held_most < sum(len(s.times) for s in whole.values())  # never every row at once
        repeats = sum(int(np.count_nonzero(np.diff(whole[e].times) == 0)) for e in ENTITIES)
        assert sum(quality.repeats.values()) == repeats
    finally:
        recording.close()
