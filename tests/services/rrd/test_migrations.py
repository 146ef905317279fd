"""Descriptors of older SDKs' chunks, migrated as the newest Rerun migrates them (re_sorbet), and the
footer manifest named after the migrated descriptors."""

from __future__ import annotations

import pyarrow as pa
import pytest

from services.rrd.chunk import chunk_meta
from services.rrd.manifest import ManifestEntry, manifest_batch, sorbet_schema
from services.rrd.messages import ArrowMessage, Compression, StoreId, StoreKind
from services.rrd.migrations import (
    CURRENT_VERSION,
    migrate_field_metadata,
    migrate_schema_metadata,
    sorbet_version,
)

V0_23 = (0, 0, 1)
V0_25 = (0, 1, 1)  # SDK 0.24 to 0.27


@pytest.mark.parametrize(
    ("metadata", "version"),
    [
        ({b"rerun.entity_path": b"/a", b"rerun.version": b"1"}, (0, 0, 1)),  # SDK 0.23
        ({b"rerun:entity_path": b"/a", b"rerun:version": b"1"}, (0, 0, 2)),  # nightlies between 0.23 and 0.24
        ({b"rerun:entity_path": b"/a", b"sorbet:version": b"0.1.1"}, (0, 1, 1)),
        ({b"rerun:entity_path": b"/a", b"sorbet:version": b"0.1.3-alpha"}, (0, 1, 3)),
        ({b"rerun:entity_path": b"/a", b"sorbet:version": b"bogus"}, CURRENT_VERSION),  # Rerun skips migrating
    ],
)
def test_sorbet_version_is_guessed_as_rerun_does(metadata: dict[bytes, bytes], version: tuple[int, int, int]):
    assert sorbet_version(metadata) == version


def test_sdk_0_23_descriptors():
    positions = {
        b"rerun.kind": b"data",
        b"rerun.archetype": b"rerun.archetypes.Points3D",
        b"rerun.archetype_field": b"positions",
        b"rerun.component": b"rerun.components.Position3D",
    }
    assert migrate_field_metadata("Position3D", positions, V0_23) == {
        b"rerun:kind": b"data",
        b"rerun:archetype": b"rerun.archetypes.Points3D",
        b"rerun:component": b"Points3D:positions",
        b"rerun:component_type": b"rerun.components.Position3D",
    }
    scalar = {
        b"rerun.archetype": b"rerun.archetypes.Scalar",
        b"rerun.archetype_field": b"scalar",
        b"rerun.component": b"rerun.components.Scalar",
    }
    migrated = migrate_field_metadata("Scalar", scalar, V0_23)
    assert migrated is not None and migrated[b"rerun:component"] == b"Scalars:scalars"
    assert migrated[b"rerun:archetype"] == b"rerun.archetypes.Scalars"
    indicator = {b"rerun.kind": b"data", b"rerun.component": b"rerun.components.Points3DIndicator"}
    assert migrate_field_metadata("Points3DIndicator", indicator, V0_23) is None  # Rerun drops indicators
    start = {
        b"rerun.archetype": b"rerun.archetypes.RecordingProperties",
        b"rerun.archetype_field": b"start_time",
        b"rerun.component": b"rerun.components.Timestamp",
    }
    migrated = migrate_field_metadata("Timestamp", start, V0_23)
    assert migrated is not None and migrated[b"rerun:component"] == b"RecordingInfo:start_time"
    assert migrate_schema_metadata(
        {b"rerun.entity_path": b"/__properties/recording", b"rerun.version": b"1", b"rerun.id": b"chunk_X"}, V0_23
    ) == {b"rerun:entity_path": b"/__properties", b"rerun:id": b"chunk_X"}


@pytest.mark.parametrize(
    ("before", "after"),
    [
        (
            {
                b"rerun:archetype": b"rerun.archetypes.Transform3D",
                b"rerun:component": b"Transform3D:axis_length",
                b"rerun:component_type": b"rerun.components.AxisLength",
            },
            {
                b"rerun:archetype": b"rerun.archetypes.TransformAxes3D",
                b"rerun:component": b"TransformAxes3D:axis_length",
                b"rerun:component_type": b"rerun.components.AxisLength",
            },
        ),
        (
            {b"rerun:archetype": b"rerun.archetypes.CoordinateFrame", b"rerun:component": b"CoordinateFrame:frame_id"},
            {b"rerun:archetype": b"rerun.archetypes.CoordinateFrame", b"rerun:component": b"CoordinateFrame:frame"},
        ),
        (
            {
                b"rerun:component": b"InstancePoses3D:translations",
                b"rerun:component_type": b"rerun.components.PoseTranslation3D",
            },
            {
                b"rerun:component": b"InstancePoses3D:translations",
                b"rerun:component_type": b"rerun.components.Translation3D",
            },
        ),
        (
            {
                b"rerun:component": b"SeriesLines:visible_series",
                b"rerun:component_type": b"rerun.components.SeriesVisible",
            },
            {b"rerun:component": b"SeriesLines:visible_series", b"rerun:component_type": b"rerun.components.Visible"},
        ),
        (
            {
                b"rerun:archetype": b"rerun.blueprint.archetypes.TableColumn",
                b"rerun:component": b"TableColumn:cell_kind",
                b"rerun:component_type": b"rerun.blueprint.components.TableCellKind",
            },
            {
                b"rerun:archetype": b"rerun.blueprint.archetypes.TableColumn",
                b"rerun:component": b"TableColumn:column_type",
                b"rerun:component_type": b"rerun.blueprint.components.ColumnType",
            },
        ),
    ],
)
def test_sdk_0_25_descriptors(before: dict[bytes, bytes], after: dict[bytes, bytes]):
    assert migrate_field_metadata("x", before, V0_25) == after
    assert migrate_field_metadata("x", before, CURRENT_VERSION) == before  # current chunks are left as written


def _chunk(version: bytes) -> ArrowMessage:
    """A one-row chunk of /world/robot with Transform3D:axis_length, as SDK 0.24-0.27 logged it."""
    md = {
        b"rerun:archetype": b"rerun.archetypes.Transform3D",
        b"rerun:component": b"Transform3D:axis_length",
        b"rerun:component_type": b"rerun.components.AxisLength",
        b"rerun:kind": b"data",
    }
    schema = pa.schema(
        [
            pa.field(
                "rerun.controls.RowId",
                pa.binary(16),
                nullable=False,
                metadata={b"rerun:kind": b"control", b"ARROW:extension:name": b"rerun.datatypes.TUID"},
            ),
            pa.field("frame", pa.int64(), metadata={b"rerun:kind": b"index", b"rerun:index_name": b"frame"}),
            pa.field("Transform3D:axis_length", pa.list_(pa.float32()), metadata=md),
        ],
        metadata={
            b"rerun:entity_path": b"/world/robot",
            b"rerun:id": b"chunk_18EA7292533BB0171bda73fcdd355478",
            b"sorbet:version": version,
        },
    )
    batch = pa.record_batch(
        [pa.array([b"\x01" * 16], pa.binary(16)), pa.array([3]), pa.array([[0.5]], pa.list_(pa.float32()))],
        schema=schema,
    )
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(batch)
    payload = sink.getvalue().to_pybytes()
    return ArrowMessage(
        0,
        0,
        0,
        b"x" * 10,
        StoreId(StoreKind.RECORDING, "app", "rec"),
        None,
        None,
        Compression.NONE,
        len(payload),
        payload,
    )


def test_manifest_names_columns_after_migrated_descriptors():
    """What `rerun rrd verify` asked for: `static index 'TransformAxes3D:axis_length:has_static_data'`."""
    meta = chunk_meta(_chunk(b"0.1.1"))
    names = manifest_batch([ManifestEntry(meta, 0)]).schema.names
    assert "TransformAxes3D:axis_length:has_static_data" in names
    assert "frame:TransformAxes3D:axis_length:start" in names
    assert not any("Transform3D:axis_length" in n for n in names)
    schema = sorbet_schema([meta])
    column = schema.field("/world/robot:TransformAxes3D:axis_length")
    assert column.metadata[b"rerun:archetype"] == b"rerun.archetypes.TransformAxes3D"
    # A chunk of a current SDK with that (today unused) descriptor is named as written.
    current = manifest_batch([ManifestEntry(chunk_meta(_chunk(b"0.1.4")), 0)]).schema.names
    assert "Transform3D:axis_length:has_static_data" in current
