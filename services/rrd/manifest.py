"""The RRD manifest: one dataframe row per chunk, written in the footer of each stream.

Mirrors the layout Rerun's own writer produces (checked in tests against footers written by the
SDK), so `rerun rrd verify`, footer readers and the catalog server can seek to any chunk:
  chunk_entity_path, chunk_id, chunk_is_static, chunk_num_rows, chunk_byte_offset (of the
  ArrowMsg payload, stream-relative), chunk_byte_size, chunk_byte_size_uncompressed;
  `<component>:has_static_data`; `<timeline>:start|end`; `<timeline>:<component>:start|end|num_rows`.
Plus the recording's Sorbet schema (every column of every entity) and its SHA-256.
Columns are named after descriptors as the reading Rerun migrates them (migrations.py), so a
footer over chunks of an older SDK names what `rerun rrd verify` and `rerun server` expect.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import lz4.block
import pyarrow as pa

from services.rrd.chunk import ChunkMeta, ComponentMeta
from services.rrd.messages import Compression, StoreId
from services.rrd.pb import common_pb2, log_msg_pb2
from services.rrd.schema_hash import sorbet_schema_sha256

PROPERTIES_ENTITY = "/__properties"


def is_property_entity(entity_path: str) -> bool:
    """The recording's properties: `/__properties` (RecordingInfo) and `/__properties/NAME`."""
    return entity_path == PROPERTIES_ENTITY or entity_path.startswith(PROPERTIES_ENTITY + "/")


_UNSAFE_CHARS = str.maketrans({c: "_" for c in ", -.\\"})


@dataclass(frozen=True, slots=True)
class ManifestEntry:
    meta: ChunkMeta
    byte_offset: int  # stream-relative offset of the ArrowMsg protobuf payload


def column_name(*parts: str | None) -> str:
    """Rerun's manifest column naming: non-empty parts joined by ':', unsafe characters -> '_'."""
    name = ":".join(p for p in parts if p)
    return name.translate(_UNSAFE_CHARS).lstrip("_")


# Rerun's short archetype names drop only its own prefixes: `rerun.archetypes.Points3D` is Points3D,
# while an importer's `sensor_msgs.msg.Imu` stays whole (its dots made `_` by column_name).
_ARCHETYPE_PREFIXES = ("rerun.blueprint.archetypes.", "rerun.archetypes.", "rerun.")


def archetype_short_name(archetype: str) -> str:
    for prefix in _ARCHETYPE_PREFIXES:
        if archetype.startswith(prefix):
            return archetype[len(prefix) :]
    return archetype


def _descriptor_parts(comp: ComponentMeta) -> tuple[str | None, str]:
    archetype_short = archetype_short_name(comp.archetype) if comp.archetype else None
    field_name = comp.component.rsplit(":", 1)[-1]
    return archetype_short, field_name


def _descriptor_metadata(comp: ComponentMeta, index: str) -> dict[bytes, bytes]:
    md = {b"rerun:index": index.encode(), b"rerun:component": comp.component.encode()}
    if comp.archetype:
        md[b"rerun:archetype"] = comp.archetype.encode()
    if comp.component_type:
        md[b"rerun:component_type"] = comp.component_type.encode()
    return md


def sorbet_column_name(entity_path: str, column: str) -> str:
    """The recording-wide column name: `/world/points:Points3D:positions`, and for recording
    properties `property:fleet:robot_id` / `property:RecordingInfo:start_time`."""
    if is_property_entity(entity_path):
        rest = entity_path[len(PROPERTIES_ENTITY) :].strip("/")
        return ":".join(p for p in ("property", rest, column) if p)
    return f"{entity_path}:{column}"


def sorbet_schema(chunks: Iterable[ChunkMeta]) -> pa.Schema:
    """The merged schema of a recording: row id, timelines, and every entity's columns."""
    fields: dict[str, pa.Field] = {}
    static_columns: set[str] = set()
    for meta in chunks:
        if meta.row_id_field is not None and meta.row_id_field.name not in fields:
            row_id = meta.row_id_field
            md = {k: v for k, v in (row_id.metadata or {}).items() if k != b"rerun:is_sorted"}
            fields[row_id.name] = row_id.with_metadata(md)
        for tl in meta.timelines:
            fields.setdefault(
                tl.name,
                pa.field(
                    tl.name, tl.field.type, metadata={b"rerun:index_name": tl.name.encode(), b"rerun:kind": b"index"}
                ),
            )
        for comp in meta.components:
            name = sorbet_column_name(meta.entity_path, comp.column)
            if meta.is_static:
                static_columns.add(name)
            if name not in fields:
                # The descriptor as the reading Rerun migrates it (see migrations.py), not as written.
                md = {b"rerun:component": comp.component.encode()}
                if comp.archetype:
                    md[b"rerun:archetype"] = comp.archetype.encode()
                if comp.component_type:
                    md[b"rerun:component_type"] = comp.component_type.encode()
                md[b"rerun:entity_path"] = meta.entity_path.encode()
                md[b"rerun:kind"] = b"data"
                fields[name] = pa.field(name, comp.field.type, metadata=md)
    for name in static_columns:
        fields[name] = fields[name].with_metadata({**(fields[name].metadata or {}), b"rerun:is_static": b"true"})
    return pa.schema([fields[name] for name in sorted(fields)])


def schema_sha256(schema: pa.Schema) -> bytes:
    """SHA-256 of the schema's IPC encoding, fields sorted by name and no schema metadata, as
    Rerun computes it (see schema_hash)."""
    return sorbet_schema_sha256(schema)


def manifest_batch(entries: list[ManifestEntry]) -> pa.RecordBatch:
    metas = [e.meta for e in entries]
    columns: dict[str, pa.Array] = {}
    fields: list[pa.Field] = []

    def add(fld: pa.Field, values: Sequence[object]) -> None:
        fields.append(fld)
        columns[fld.name] = pa.array(values, type=fld.type)

    u64 = pa.uint64()
    add(pa.field("chunk_entity_path", pa.utf8(), nullable=False), [m.entity_path for m in metas])
    add(pa.field("chunk_id", pa.binary(16), nullable=False), [m.chunk_id for m in metas])
    add(pa.field("chunk_is_static", pa.bool_(), nullable=False), [m.is_static for m in metas])
    add(pa.field("chunk_num_rows", u64, nullable=False), [m.num_rows for m in metas])
    add(pa.field("chunk_byte_offset", u64, nullable=False), [e.byte_offset for e in entries])
    add(pa.field("chunk_byte_size", u64, nullable=False), [m.byte_size for m in metas])
    add(pa.field("chunk_byte_size_uncompressed", u64, nullable=False), [m.uncompressed_size for m in metas])

    descriptors: dict[tuple[str, str, str], ComponentMeta] = {}
    timeline_types: dict[str, pa.DataType] = {}
    for meta in metas:
        for comp in meta.components:
            descriptors.setdefault(comp.descriptor, comp)
        for tl in meta.timelines:
            timeline_types.setdefault(tl.name, tl.field.type)

    by_descriptor = [{c.descriptor: c for c in m.components} for m in metas]
    seen: set[str] = set()
    for key in sorted(descriptors, key=lambda d: (d[0] != "", d)):
        comp = descriptors[key]
        name = column_name(*_descriptor_parts(comp), "has_static_data")
        if name in seen:
            continue
        seen.add(name)
        md = {k: v for k, v in _descriptor_metadata(comp, "rerun:static").items()}
        add(
            pa.field(name, pa.bool_(), nullable=False, metadata=md),
            [m.is_static and key in comps for m, comps in zip(metas, by_descriptor, strict=True)],
        )

    for tl_name in sorted(timeline_types):
        tl_type = timeline_types[tl_name]
        md = {b"rerun:index": tl_name.encode()}
        ranges = [next((t.range for t in m.timelines if t.name == tl_name), None) for m in metas]
        add(pa.field(column_name(tl_name, "start"), tl_type, metadata=md), [r.min if r else None for r in ranges])
        add(pa.field(column_name(tl_name, "end"), tl_type, metadata=md), [r.max if r else None for r in ranges])

    for tl_name in sorted(timeline_types):
        tl_type = timeline_types[tl_name]
        for key in sorted(descriptors, key=lambda d: (d[0] != "", d)):
            per_chunk = [comps.get(key) for comps in by_descriptor]
            comp_ranges = [c.ranges.get(tl_name) if c is not None else None for c in per_chunk]
            if not any(comp_ranges):
                continue
            comp = descriptors[key]
            md = _descriptor_metadata(comp, tl_name)
            base = column_name(tl_name, *_descriptor_parts(comp))
            if base + ":start" in seen:
                continue
            seen.add(base + ":start")
            add(pa.field(base + ":start", tl_type, metadata=md), [r.min if r else None for r in comp_ranges])
            add(pa.field(base + ":end", tl_type, metadata=md), [r.max if r else None for r in comp_ranges])
            rows = [
                c.num_rows if c is not None and r is not None else 0
                for c, r in zip(per_chunk, comp_ranges, strict=True)
            ]
            add(pa.field(base + ":num_rows", u64, metadata=md), rows)

    return pa.RecordBatch.from_arrays([columns[f.name] for f in fields], schema=pa.schema(fields))


def build_manifest(store_id: StoreId, entries: list[ManifestEntry]) -> log_msg_pb2.RrdManifest:
    schema = sorbet_schema(e.meta for e in entries)
    batch = manifest_batch(entries)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    ipc = sink.getvalue().to_pybytes()
    return log_msg_pb2.RrdManifest(
        store_id=store_id.to_proto(),
        sorbet_schema=common_pb2.Schema(arrow_schema=schema.serialize().to_pybytes()),
        sorbet_schema_sha256=schema_sha256(schema),
        data=common_pb2.DataframePart(
            encoder_version=common_pb2.ENCODER_VERSION_V0,
            payload=lz4.block.compress(ipc, store_size=False),
            compression=int(Compression.LZ4),  # type: ignore[arg-type]
            uncompressed_size=len(ipc),
        ),
    )


def read_manifest(manifest: log_msg_pb2.RrdManifest) -> pa.Table:
    """The manifest dataframe of one store, as written by any Rerun writer."""
    raw = manifest.data.payload
    if int(manifest.data.compression) == Compression.LZ4:
        raw = lz4.block.decompress(raw, uncompressed_size=manifest.data.uncompressed_size)
    return pa.ipc.open_stream(raw).read_all()


def read_sorbet_schema(manifest: log_msg_pb2.RrdManifest) -> pa.Schema:
    return pa.ipc.read_schema(pa.py_buffer(manifest.sorbet_schema.arrow_schema))
