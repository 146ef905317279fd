"""Rerun's column order and schema merge, as its chunk store and server apply them (the golden
tests in test_query.py compare whole answers with `rerun server`; these pin the rules)."""

from __future__ import annotations

import functools
import random

import pyarrow as pa
import pytest

from services.redap.schema import (
    compare_entity_paths,
    entity_parts,
    merge_schemas,
    natural_compare,
    rerun_order,
)


@pytest.mark.parametrize(
    "ordered",
    [  # Rerun's own natural-ordering test cases (re_log_types), in order
        ["10", "a", "aa", "b", "c"],
        ["a", "a0", "a1", "a1a", "a1b", "a2", "a10", "a20"],
        ["1.001", "1.002", "1.010", "1.02", "1.1", "1.3"],
        ["a 2", "a2"],
        ["a", "B", "b", "c"],
        ["cam2", "cam10", "cam11", "cam100"],
        ["Cam11", "cam2"],  # case decides at the first letter that differs only by case
    ],
)
def test_natural_order_is_rerun_s(ordered: list[str]):
    shuffled = random.Random(7).sample(ordered, len(ordered))
    assert sorted(shuffled, key=functools.cmp_to_key(natural_compare)) == ordered
    for i, a in enumerate(ordered):
        for j, b in enumerate(ordered):
            assert natural_compare(a, b) == (i > j) - (i < j), (a, b)


def test_reserved_entity_parts_sort_after_every_other():
    paths = ["/__properties", "/world", "/a/__x", "/a/b", "/__properties/fleet", "/zebra/2", "/zebra/10"]
    ordered = sorted(paths, key=functools.cmp_to_key(compare_entity_paths))
    assert ordered == ["/a/b", "/a/__x", "/world", "/zebra/2", "/zebra/10", "/__properties", "/__properties/fleet"]


def test_entity_parts_are_unescaped():
    assert entity_parts("/world/a\\/b/c") == ["world", "a/b", "c"]
    assert entity_parts("world/points/") == ["world", "points"]


def _component(entity: str, component: str, archetype: str | None = None, **more: str) -> pa.Field:
    metadata = {"rerun:kind": "data", "rerun:entity_path": entity, "rerun:component": component, **more}
    if archetype:
        metadata["rerun:archetype"] = archetype
    column = f"{entity}:{component}" if not entity.startswith("/__properties") else f"property:{component}"
    return pa.field(column, pa.list_(pa.float32()), metadata=metadata)


ROW_ID = pa.field("rerun.controls.RowId", pa.binary(16), nullable=False, metadata={"rerun:kind": "control"})


def _index(name: str) -> pa.Field:
    return pa.field(name, pa.int64(), metadata={"rerun:kind": "index", "rerun:index_name": name})


def test_a_run_s_columns_come_row_id_then_timelines_then_components_by_entity_archetype_component():
    fields = [
        _component("/__properties", "RecordingInfo:start_time", "rerun.archetypes.RecordingInfo"),
        _component("/world/cam10", "Image:buffer", "rerun.archetypes.Image"),
        _index("sim"),
        _component("/world/cam2", "Image:format", "rerun.archetypes.Image"),
        ROW_ID,
        _component("/world/cam2", "Image:buffer", "rerun.archetypes.Image"),
        _component("/world/cam2", "custom", None),  # no archetype: before those with one
        _index("frame"),
    ]
    ordered = rerun_order(pa.schema(fields, metadata={"sorbet:version": "0.1.4"}))
    assert ordered.names == [
        "rerun.controls.RowId",
        "frame",
        "sim",
        "/world/cam2:custom",
        "/world/cam2:Image:buffer",
        "/world/cam2:Image:format",
        "/world/cam10:Image:buffer",
        "property:RecordingInfo:start_time",
    ]
    assert ordered.metadata is None


def test_runs_merge_in_first_seen_order_with_their_metadata_joined():
    temporal = _component("/world/label", "TextLog:text", "rerun.archetypes.TextLog")
    static = temporal.with_metadata({**temporal.metadata, b"rerun:is_static": b"true"})
    first = pa.schema([ROW_ID, _index("frame"), temporal])
    second = pa.schema([ROW_ID, _index("frame"), _index("tick"), static.with_nullable(True)])
    merged = merge_schemas([first, second])
    assert merged.names == ["rerun.controls.RowId", "frame", "/world/label:TextLog:text", "tick"]
    assert merged.field("/world/label:TextLog:text").metadata[b"rerun:is_static"] == b"true"
    assert merge_schemas([]).names == []


def test_a_column_typed_apart_in_two_runs_keeps_the_first_run_s_type():
    first = pa.schema([pa.field("/a:x", pa.list_(pa.float32()), metadata={"rerun:kind": "data"})])
    second = pa.schema([pa.field("/a:x", pa.list_(pa.float64()), metadata={"rerun:kind": "data"})])
    assert merge_schemas([first, second]).field("/a:x").type == pa.list_(pa.float32())
