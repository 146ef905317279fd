"""`chunks.parquet`: per-component ranges round-trip, and indexes written before them still load."""

from __future__ import annotations

import io

import pyarrow.parquet as pq

from services.sealed.index import CHUNK, ComponentRange, IndexRow, TimelineRange, from_parquet, to_parquet

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
