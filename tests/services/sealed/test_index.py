"""`chunks.parquet`: per-component ranges round-trip, indexes written before them still load, and an
index read as columns makes the same rows, and works out the same groups, timelines and entities,
as its rows do."""

from __future__ import annotations

import gc
import io
from dataclasses import replace

import pyarrow.parquet as pq

from services.sealed.index import (
    BLUEPRINT_ACTIVATION,
    CHUNK,
    STORE_INFO,
    ComponentRange,
    IndexRow,
    TimelineRange,
    from_parquet,
    read_index,
    to_parquet,
)

ROW = IndexRow(
    CHUNK,
    "recording",
    12,
    300,
    b"\x01" * 16,
    "/robot",
    False,
    4,
    (TimelineRange("frame", "sequence", 0, 30),),
    ("Points3D:colors", "Points3D:positions"),
    (ComponentRange("Points3D:colors", "frame", 0, 20, 2), ComponentRange("Points3D:positions", "frame", 0, 30, 4)),
)


def test_component_ranges_round_trip():
    assert from_parquet(to_parquet([ROW])) == [ROW]
    table = pq.read_table(io.BytesIO(to_parquet([ROW])))
    assert table.column("component_ranges").to_pylist()[0][0] == {
        "component": "Points3D:colors",
        "timeline": "frame",
        "min": 0,
        "max": 20,
        "rows": 2,
    }


def test_an_index_from_before_component_ranges_loads_with_them_unknown():
    old = pq.read_table(io.BytesIO(to_parquet([ROW]))).drop_columns(["component_ranges"])
    out = io.BytesIO()
    pq.write_table(old, out)
    (row,) = from_parquet(out.getvalue())
    assert row.component_ranges is None and row.timelines == ROW.timelines and row.components == ROW.components


def test_rows_of_every_shape_round_trip_in_order():
    """Rows are read column by column, nested lists cut per row: rows without timelines, components
    or ranges, with empty and unknown ranges, store infos and blueprints keep their own values."""
    rows = [
        IndexRow(STORE_INFO, "recording", 8, 40),
        ROW,
        IndexRow(CHUNK, "recording", 312, 90, b"\x02" * 16, "/static", True, 1, (), ("Text:text",), ()),
        IndexRow(CHUNK, "blueprint", 402, 70, b"\x03" * 16, "/view", False, 2, (), (), None),
        IndexRow(BLUEPRINT_ACTIVATION, "blueprint", 472, 30),
        IndexRow(
            CHUNK,
            "recording",
            502,
            500,
            b"\x04" * 16,
            "/robot/arm",
            False,
            7,
            (TimelineRange("frame", "sequence", 5, 9), TimelineRange("log_time", "timestamp", -3, 10**18)),
            ("Scalars:scalars",),
            (ComponentRange("Scalars:scalars", "log_time", -3, 10**18, 7),),
        ),
    ]
    table = pq.read_table(io.BytesIO(to_parquet(rows)))
    out = io.BytesIO()
    pq.write_table(table, out, row_group_size=2)  # read back as several chunks of each column
    assert from_parquet(out.getvalue()) == rows


def test_a_big_index_reads_back_the_same_rows_as_plain_values():
    """Past a few rows, names repeat and are made once per distinct value, numbers come from numpy:
    the rows are equal all the same, and hold Python's own str, int and bool (never numpy's)."""
    rows = [
        replace(ROW, offset=12 + 300 * i, chunk_id=i.to_bytes(16, "big"), entity_path=f"/robot/{i % 3}")
        if i % 10
        else IndexRow(STORE_INFO, "recording", 12 + 300 * i, 300)
        for i in range(1000)
    ]
    back = from_parquet(to_parquet(rows))
    assert back == rows
    chunk = back[1]
    assert type(chunk.offset) is int and type(chunk.is_static) is bool and type(chunk.entity_path) is str
    assert type(chunk.timelines[0].min) is int and type(chunk.component_ranges[0].rows) is int  # type: ignore[index]
    assert back[0].entity_path is None and back[0].chunk_id is None


def test_the_parse_leaves_the_garbage_collector_as_it_found_it():
    data = to_parquet([ROW] * 100)
    assert gc.isenabled()
    from_parquet(data)
    assert gc.isenabled()
    gc.disable()
    try:
        from_parquet(data)
        assert not gc.isenabled()
    finally:
        gc.enable()


def _mixed_rows(count: int) -> list[IndexRow]:
    """Chunks of three entities (one without timelines, one static), a blueprint's, store infos."""
    rows: list[IndexRow] = []
    for i in range(count):
        at = 12 + 300 * i
        if i % 10 == 0:
            rows.append(IndexRow(STORE_INFO, "recording" if i % 20 else "blueprint", at, 300))
        elif i % 10 == 7:
            rows.append(IndexRow(CHUNK, "blueprint", at, 300, i.to_bytes(16, "big"), "/view", False, 1, (), (), None))
        else:
            timeline = (
                TimelineRange("log_time", "timestamp", i, i + 5)
                if i % 3 == 0
                else TimelineRange("frame", "sequence", i, i + 2)
            )
            rows.append(
                replace(
                    ROW,
                    offset=at,
                    chunk_id=i.to_bytes(16, "big"),
                    entity_path=f"/robot/{i % 3}",
                    is_static=i % 10 == 9,
                    timelines=(timeline,) if i % 10 != 9 else (),
                )
            )
    return rows


def test_an_index_read_as_columns_makes_the_rows_it_is_asked_for():
    rows = _mixed_rows(200)
    index = read_index(to_parquet(rows))
    assert len(index) == len(rows)
    assert index.at([150, 3, 3, 77]) == [rows[150], rows[3], rows[3], rows[77]]
    assert index[5] == rows[5] and index[-1] == rows[-1] and index[10:13] == rows[10:13]
    assert list(index) == rows  # every row, then served from them
    assert index.at([4, 0]) == [rows[4], rows[0]]


def test_an_index_read_as_columns_works_out_what_its_rows_say():
    rows = _mixed_rows(300)
    index = read_index(to_parquet(rows))
    by_entity, blueprint_chunks, others = index.groups()
    expected: dict[str, list[int]] = {}
    for i, row in enumerate(rows):
        if row.kind == CHUNK and row.store_kind == "recording":
            expected.setdefault(row.entity_path or "", []).append(i)
    assert by_entity == expected
    assert blueprint_chunks == [i for i, r in enumerate(rows) if r.kind == CHUNK and r.store_kind == "blueprint"]
    assert others == [i for i, r in enumerate(rows) if r.kind != CHUNK]
    assert index.timeline_types() == {"frame": "sequence", "log_time": "timestamp"}
    assert index.entity_paths() == {r.entity_path for r in rows if r.kind == CHUNK and r.entity_path}
    empty = read_index(to_parquet([IndexRow(STORE_INFO, "recording", 8, 40)]))
    assert empty.groups() == ({}, [], [0]) and empty.timeline_types() == {} and empty.entity_paths() == set()
