"""A time window on a sealed run's index read as columns makes the rows of the chunks it may keep
only (`latest_at.may_keep`), and keeps what it keeps when it goes over all of its entities'
chunks: windows anywhere in a run, open or closed, with and without latest-at, over sparse and
overlapping components, static and blueprint chunks, a second timeline; an index from before
per-component ranges goes over all of them, as before."""

from __future__ import annotations

import io
import random

import pyarrow.parquet as pq
import pytest

from services.runs.download import EntityFilter, TimeWindow
from services.runs.indexed import _entry, _PlanIndex
from services.runs.latest_at import ChunkEntry, may_keep, select_chunks
from services.sealed.index import (
    CHUNK,
    STORE_INFO,
    ComponentRange,
    IndexRow,
    IndexTable,
    TimelineRange,
    read_index,
    to_parquet,
)

ENTITIES = ("/robot/battery", "/robot/pose", "/camera/front")
COMPONENTS = ("Scalars:scalars", "Transform3D:translation", "Image:buffer", "Image:format")


def a_run(seed: int, chunks: int = 600) -> list[IndexRow]:
    """An index of `chunks` chunks of three entities on `frame` (and some on `log_time` too), with
    gaps, overlaps, sparse components, static chunks and a blueprint."""
    rng = random.Random(seed)
    rows = [IndexRow(STORE_INFO, "recording", 0, 20)]
    clock = dict.fromkeys(ENTITIES, 0)
    for n in range(chunks):
        entity = rng.choice(ENTITIES)
        store = "blueprint" if rng.random() < 0.02 else "recording"
        static = rng.random() < 0.03
        first = max(0, clock[entity] + rng.randint(-8, 25))  # overlapping its predecessor now and then
        last = first + rng.randint(0, 30)
        clock[entity] = last
        timelines: tuple[TimelineRange, ...] = () if static else (TimelineRange("frame", "sequence", first, last),)
        if timelines and rng.random() < 0.3:
            timelines += (TimelineRange("log_time", "timestamp", first * 10, last * 10),)
        components = tuple(sorted(rng.sample(COMPONENTS, rng.randint(1, 3))))
        ranges = []
        for component in components:
            if timelines and rng.random() < 0.8:  # a sparse one holds a part of the chunk's rows
                lo = rng.randint(first, last)
                hi = rng.randint(lo, last)
                ranges.append(ComponentRange(component, "frame", lo, hi, 1))
                if len(timelines) > 1:  # the same rows on the other timeline: other numbers, not to be mixed
                    ranges.append(ComponentRange(component, "log_time", lo * 10, hi * 10, 1))
        rows.append(
            IndexRow(
                CHUNK,
                store,
                20 + n * 100,
                100,
                n.to_bytes(16, "big"),
                entity,
                static,
                last - first + 1,
                timelines,
                components,
                tuple(ranges),
            )
        )
    return rows


def chosen(
    table: IndexTable, positions: list[int], window: TimeWindow
) -> tuple[tuple[set[bytes], set[bytes]], list[ChunkEntry]]:
    entries = [_entry(row, window.timeline) for row in table.at(positions)]

    def unread(_: list[ChunkEntry]) -> list[ChunkEntry]:
        raise AssertionError("every chunk's component ranges are in the index: none is read")

    return select_chunks(entries, window.bounds, window.latest_at, unread), entries


def windows(seed: int) -> list[TimeWindow]:
    rng = random.Random(seed)
    out = [TimeWindow("frame", None, None), TimeWindow("frame", None, 40), TimeWindow("frame", 3000, None)]
    for _ in range(40):
        start = rng.randint(-10, 4000)
        out.append(TimeWindow("frame", start, start + rng.randint(0, 300), latest_at=rng.random() < 0.7))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_a_window_keeps_from_the_chunks_it_may_keep_what_it_keeps_from_all(seed: int):
    table = read_index(to_parquet(a_run(seed)))
    plan = _PlanIndex.of(table)
    made, every = 0, 0
    for include in (["/robot/battery"], ["/robot/**"], []):
        positions = plan.chunks(EntityFilter(include))
        for window in windows(seed):
            narrowed = plan.window_chunks(positions, window)
            assert set(narrowed) <= set(positions) and narrowed == sorted(narrowed)
            assert chosen(table, narrowed, window)[0] == chosen(table, positions, window)[0], (include, window)
            made, every = made + len(narrowed), every + len(positions)
    assert made < every / 3  # the point: most of an entity's chunks are not made into rows


def test_a_closed_window_without_latest_at_keeps_exactly_its_overlapping_static_and_blueprint_chunks():
    rows = a_run(7)
    table = read_index(to_parquet(rows))
    positions = _PlanIndex.of(table).chunks(EntityFilter())
    window = TimeWindow("frame", 1000, 1100, latest_at=False)
    expected = [
        i
        for i in positions
        if rows[i].store_kind != "recording"
        or rows[i].is_static
        or any(t.name == "frame" and t.max >= 1000 and t.min <= 1100 for t in rows[i].timelines)
    ]
    kept = may_keep(table, positions, "frame", window.bounds, False)
    assert kept is not None and [positions[i] for i in kept.nonzero()[0]] == expected


def test_an_index_from_before_component_ranges_plans_over_every_chunk():
    old = pq.read_table(io.BytesIO(to_parquet(a_run(8)))).drop_columns(["component_ranges"])
    out = io.BytesIO()
    pq.write_table(old, out)
    table = read_index(out.getvalue())
    plan = _PlanIndex.of(table)
    positions = plan.chunks(EntityFilter(["/robot/battery"]))
    window = TimeWindow("frame", 2000, 2100)  # latest-at: the chunks before it must be read to tell
    assert may_keep(table, positions, "frame", window.bounds, True) is None
    assert plan.window_chunks(positions, window) == positions
    without = TimeWindow("frame", 2000, 2100, latest_at=False)  # what overlaps is in the columns
    assert len(plan.window_chunks(positions, without)) < len(positions) / 3
