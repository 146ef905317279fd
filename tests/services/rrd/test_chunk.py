"""chunk_meta on every chunk of every real recording, checked against what was logged, against the
Arrow data read independently, and against the SDK's own footer manifest."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import lz4.block
import numpy as np
import pyarrow as pa
import pytest

from services.rrd import ArrowMessage, EndMessage, StoreKind, chunk_meta, iter_events
from services.rrd.chunk import ChunkMeta, parse_chunk_id
from services.rrd.messages import chunk_id_str, tuid_bytes
from services.rrd.pb import log_msg_pb2
from tests.services.rrd.recordings import Recording, walk_frames

pytestmark = pytest.mark.sdk

ARROW_TYPES = {"sequence": pa.int64(), "timestamp": pa.timestamp("ns"), "duration": pa.duration("ns")}


def chunks_by_recording(rec: Recording) -> dict[str, list[tuple[ArrowMessage, ChunkMeta]]]:
    """recording id -> (message, metadata) of each chunk of that recording store."""
    out: dict[str, list[tuple[ArrowMessage, ChunkMeta]]] = defaultdict(list)
    for event in iter_events(rec.path):
        if isinstance(event, ArrowMessage) and event.store_id.kind == StoreKind.RECORDING:
            out[event.store_id.recording_id].append((event, chunk_meta(event)))
    return out


def all_chunks(rec: Recording) -> list[tuple[ArrowMessage, ChunkMeta]]:
    return [(e, chunk_meta(e)) for e in iter_events(rec.path) if isinstance(e, ArrowMessage)]


def independent_batch(msg: ArrowMessage) -> tuple[pa.RecordBatch, log_msg_pb2.ArrowMsg, bytes]:
    """The chunk read straight from the protobuf bytes, without services.rrd.chunk."""
    pb = log_msg_pb2.ArrowMsg.FromString(bytes(msg.raw))
    assert pb.compression == 2  # LZ4: what 0.41 writes
    ipc = lz4.block.decompress(pb.payload, uncompressed_size=pb.uncompressed_size)
    table = pa.ipc.open_stream(ipc).read_all()
    batches = table.to_batches()
    assert len(batches) == 1
    return batches[0], pb, ipc


def _kind(field: pa.Field) -> bytes | None:
    return (field.metadata or {}).get(b"rerun:kind")


def _int_values(column: pa.Array) -> np.ndarray:
    return np.array([v for v in column.cast(pa.int64()).to_pylist() if v is not None], dtype=np.int64)


# --- against the ground truth ----------------------------------------------------------------


def test_chunks_match_what_was_logged(whole: Recording):
    by_recording = chunks_by_recording(whole)
    assert set(by_recording) == {r["recording_id"] for r in whole.recordings}
    for truth in whole.recordings:
        chunks = by_recording[truth["recording_id"]]
        entities: dict[str, Any] = truth["entities"]
        assert {meta.entity_path for _, meta in chunks} == set(entities)
        for path, expected in entities.items():
            metas = [meta for _, meta in chunks if meta.entity_path == path]
            static = [m for m in metas if m.is_static]
            temporal = [m for m in metas if not m.is_static]
            assert sum(m.num_rows for m in static) == expected["static_rows"], path
            assert sum(m.num_rows for m in temporal) == expected["temporal_rows"], path
            assert set().union(*(m.archetypes for m in metas)) == set(expected["archetypes"]), path
            assert {c.component for m in metas for c in m.components} == set(expected["components"]), path
            for component, rows in expected["component_rows"].items():
                assert sum(c.num_rows for m in metas for c in m.components if c.component == component) == rows

            for m in static:
                assert m.timelines == ()
            lo, hi = truth["log_time"]
            for m in temporal:
                assert {t.name for t in m.timelines} == set(expected["timelines"]) | {"log_time"}, path
                for tl in m.timelines:
                    if tl.name == "log_time":  # set by the SDK at each log call
                        assert tl.type == "timestamp"
                        assert lo <= tl.range.min <= tl.range.max <= hi
                    else:
                        want = expected["timelines"][tl.name]
                        assert tl.type == want["type"]
                        assert want["min"] <= tl.range.min <= tl.range.max <= want["max"]
                    assert tl.field.type == ARROW_TYPES[tl.type]
            for name, want in expected["timelines"].items():
                ranges = [t.range for m in temporal for t in m.timelines if t.name == name]
                assert min(r.min for r in ranges) == want["min"], (path, name)
                assert max(r.max for r in ranges) == want["max"], (path, name)


def test_static_flag_matches_arrow_msg(whole: Recording):
    for msg, meta in all_chunks(whole):
        assert msg.is_static is not None
        assert meta.is_static == msg.is_static


def test_properties_chunks(recordings: dict[str, Recording]):
    rec = recordings["properties"]
    truth = rec.recordings[0]
    chunks = chunks_by_recording(rec)[truth["recording_id"]]
    for name, values in truth["properties"].items():
        ((msg, meta),) = [(msg, meta) for msg, meta in chunks if meta.entity_path == f"/__properties/{name}"]
        assert meta.is_static and meta.num_rows == 1
        assert {c.column for c in meta.components} == set(values)
        assert all(c.archetype is None for c in meta.components)
        batch, _, _ = independent_batch(msg)
        for field, value in values.items():
            assert batch.column(field).to_pylist() == [[value]]
    ((_, info),) = [(msg, meta) for msg, meta in chunks if meta.entity_path == "/__properties"]
    assert [c.column for c in info.components] == ["RecordingInfo:start_time"]
    assert info.components[0].component_type == "rerun.components.Timestamp"


def test_unsorted_chunks_have_true_ranges(recordings: dict[str, Recording]):
    """The scalars scene logs `step` out of order: ranges come from min/max, not first/last."""
    rec = recordings["scalars"]
    temporal = [meta for _, meta in all_chunks(rec) if not meta.is_static]
    steps = [t for m in temporal for t in m.timelines if t.name == "step"]
    assert any(not t.is_sorted for t in steps)
    for msg, meta in all_chunks(rec):
        batch, _, _ = independent_batch(msg)
        for tl in meta.timelines:
            values = _int_values(batch.column(tl.field.name))
            assert (tl.range.min, tl.range.max) == (values.min(), values.max())


# --- against the Arrow data, read independently ---------------------------------------------


def test_chunk_meta_matches_arrow_data(whole: Recording):
    data = whole.data
    frames = {f.offset: f for f in walk_frames(data)[0]}
    for msg, meta in all_chunks(whole):
        batch, pb, ipc = independent_batch(msg)
        schema_meta = batch.schema.metadata
        assert meta.entity_path == schema_meta[b"rerun:entity_path"].decode()
        id_text = schema_meta[b"rerun:id"].decode()
        assert id_text.startswith("chunk_")
        assert meta.chunk_id == bytes.fromhex(id_text.removeprefix("chunk_"))
        assert meta.chunk_id == parse_chunk_id(id_text)
        assert chunk_id_str(meta.chunk_id) == id_text
        assert pb.HasField("chunk_id") and meta.chunk_id == tuid_bytes(pb.chunk_id)
        assert meta.num_rows == batch.num_rows

        assert meta.byte_size == len(msg.raw) == frames[msg.offset].length
        assert meta.uncompressed_size == pb.uncompressed_size == len(ipc)

        control = [f for f in batch.schema if _kind(f) == b"control"]
        assert meta.row_id_field is not None and [meta.row_id_field] == control
        assert meta.row_id_field.name == "rerun.controls.RowId"

        index_fields = [f for f in batch.schema if _kind(f) == b"index"]
        assert [t.field for t in meta.timelines] == index_fields
        timeline_values = {}
        for tl in meta.timelines:
            column = batch.column(tl.field.name)
            values = _int_values(column)
            timeline_values[tl.name] = column
            assert tl.name == tl.field.metadata[b"rerun:index_name"].decode()
            assert (tl.range.min, tl.range.max) == (values.min(), values.max())
            assert tl.is_sorted == (tl.field.metadata.get(b"rerun:is_sorted") == b"true")
            assert (
                tl.type
                == {"int64": "sequence", "timestamp[ns]": "timestamp", "duration[ns]": "duration"}[str(tl.field.type)]
            )
        assert meta.is_static == (not index_fields)

        data_fields = [f for f in batch.schema if _kind(f) == b"data"]
        assert [c.field for c in meta.components] == data_fields
        for comp in meta.components:
            fmeta = comp.field.metadata
            column = batch.column(comp.column)
            assert comp.component == fmeta[b"rerun:component"].decode()
            assert comp.archetype == (fmeta[b"rerun:archetype"].decode() if b"rerun:archetype" in fmeta else None)
            assert comp.component_type == (
                fmeta[b"rerun:component_type"].decode() if b"rerun:component_type" in fmeta else None
            )
            assert comp.num_rows == len(column) - column.null_count
            valid = column.is_valid()
            for name, index_column in timeline_values.items():
                values = _int_values(index_column.filter(valid))
                assert (comp.ranges[name].min, comp.ranges[name].max) == (values.min(), values.max())
            assert set(comp.ranges) == set(timeline_values)


def test_a_component_with_null_cells(recordings: dict[str, Recording]):
    """The points scene leaves out colors in some rows; `rerun rrd optimize` compacts them into one
    chunk whose colors column has null cells: num_rows and ranges count only the others."""
    truth = recordings["optimized"].recordings[0]["entities"]["/world/points"]
    assert truth["component_rows"]["Points3D:colors"] < truth["temporal_rows"]
    metas = [meta for _, meta in all_chunks(recordings["optimized"]) if meta.entity_path == "/world/points"]
    colors = [c for m in metas for c in m.components if c.component == "Points3D:colors"]
    positions = [c for m in metas for c in m.components if c.component == "Points3D:positions"]
    assert sum(c.num_rows for c in colors) == truth["component_rows"]["Points3D:colors"]
    assert sum(c.num_rows for c in positions) == truth["temporal_rows"]
    assert any(c.num_rows < m.num_rows for m in metas for c in m.components if c.component == "Points3D:colors")


# --- against the SDK's footer manifest -------------------------------------------------------


def _sdk_manifests(rec: Recording) -> list[pa.Table]:
    end = next(e for e in iter_events(rec.path) if isinstance(e, EndMessage))
    assert end.footer is not None
    tables = []
    for manifest in end.footer.manifests:
        raw = manifest.data.payload
        if manifest.data.compression == 2:
            raw = lz4.block.decompress(raw, uncompressed_size=manifest.data.uncompressed_size)
        table = pa.ipc.open_stream(raw).read_all()
        # Timelines as plain int64 (pyarrow cannot turn ns timestamps into datetime objects).
        tables.append(
            pa.table(
                [c.cast(pa.int64()) if pa.types.is_temporal(c.type) else c for c in table.columns],
                names=table.column_names,
            )
        )
    return tables


def test_chunk_meta_matches_sdk_manifest(footer_file: Recording):
    rows: dict[bytes, dict[str, Any]] = {}
    for table in _sdk_manifests(footer_file):
        for row in table.to_pylist():
            rows[row["chunk_id"]] = row
    chunks = all_chunks(footer_file)
    assert len(chunks) == len(rows)
    for msg, meta in chunks:
        row = rows[meta.chunk_id]
        assert row["chunk_entity_path"] == meta.entity_path
        assert row["chunk_is_static"] == meta.is_static
        assert row["chunk_num_rows"] == meta.num_rows
        assert row["chunk_byte_offset"] == msg.stream_payload_offset
        assert row["chunk_byte_size"] == meta.byte_size
        assert row["chunk_byte_size_uncompressed"] == meta.uncompressed_size
        for tl in meta.timelines:
            assert [row[f"{tl.name}:start"], row[f"{tl.name}:end"]] == [tl.range.min, tl.range.max], tl.name
        named = {tl.name for tl in meta.timelines}
        for key, value in row.items():
            if key.endswith(":start") and key.count(":") == 1 and key[:-6] not in named:
                assert value is None, key
