"""Reading the values of a chunk's record batch as numpy: the first instance of each row of a
component column, a column of vectors, rotations, and the chunk's timelines.

Only for a batch from `validate.validated_batch` (every value checked: reading never goes out of
bounds). Analytics extraction (Scalars, TextLog, Transform3D tables) and the rules' evaluation read
chunks through these, so both see the same values.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from services.rrd.chunk import ChunkMeta
from services.rrd.fieldmeta import rerun_key

SCALARS = "Scalars:scalars"  # older SDKs' Scalar:scalar is migrated to this name in a chunk's layout
TEXT, LEVEL = "TextLog:text", "TextLog:level"
TRANSLATION, QUATERNION, AXIS_ANGLE = (
    "Transform3D:translation",
    "Transform3D:quaternion",
    "Transform3D:rotation_axis_angle",
)


def timelines(batch: pa.RecordBatch) -> dict[str, pa.Array]:
    """The batch's index columns by timeline name (from the fields' metadata)."""
    out = {}
    for i, fld in enumerate(batch.schema):
        if rerun_key(fld, "kind") == b"index":
            out[rerun_key(fld, "index_name", fld.name.encode()).decode()] = batch.column(i)
    return out


def data_columns(batch: pa.RecordBatch, meta: ChunkMeta) -> dict[str, pa.Array]:
    """The batch's data columns by their component as Rerun reads it (the chunk's layout: a column an
    older SDK wrote goes by its migrated component, e.g. `Scalar:scalar` as `Scalars:scalars`)."""
    return {col.component: batch.column(col.position) for col in meta.layout.data}


def index_columns(batch: pa.RecordBatch, meta: ChunkMeta) -> dict[str, tuple[str, np.ndarray, np.ndarray]]:
    """Each timeline of the chunk: (sequence | timestamp | duration, its values as int64 (timestamps
    and durations in nanoseconds), which rows have one)."""
    out = {}
    for ix in meta.layout.indexes:
        out[ix.name] = (ix.type, *int64_values(batch.column(ix.position)))
    return out


def int64_values(column: pa.Array) -> tuple[np.ndarray, np.ndarray]:
    """An int64 / timestamp / duration column as int64 (nanoseconds for the time types; nulls as 0)
    and its validity."""
    kind = column.type
    if pa.types.is_timestamp(kind) and kind.unit != "ns":
        column = pc.cast(column, pa.timestamp("ns", kind.tz))
    elif pa.types.is_duration(kind) and kind.unit != "ns":
        column = pc.cast(column, pa.duration("ns"))
    as_int = column.view(pa.int64()) if column.type != pa.int64() else column
    if as_int.null_count == 0:  # the usual case, read without a compute kernel (a rule's cost per chunk)
        return as_int.to_numpy(zero_copy_only=True).astype(np.int64, copy=False), np.ones(len(as_int), dtype=bool)
    valid = np.asarray(column.is_valid(), dtype=bool)
    values = np.asarray(as_int.fill_null(0).to_numpy(zero_copy_only=False), dtype=np.int64)
    return values, valid


def first_instances(column: pa.Array) -> tuple[pa.Array, np.ndarray]:
    """The first instance of each row of a list column (null where the row has none), and which rows have one."""
    offsets = np.asarray(column.offsets)
    valid = np.asarray(column.is_valid())
    has = valid & (offsets[1:] > offsets[:-1])
    values = column.values
    first = (
        values.take(pa.array(np.where(has, offsets[:-1], 0).astype(np.int64)))
        if len(values)
        else pa.nulls(len(column), values.type)
    )
    return pc.if_else(pa.array(has), first, pa.nulls(len(column), values.type)), has


def first_floats(column: pa.Array) -> np.ndarray:
    """The first instance of each row of a numeric list column as float64: NaN where the row has none
    (or holds null)."""
    values = column.values
    if values.null_count or not (pa.types.is_floating(values.type) or pa.types.is_integer(values.type)):
        first, _ = first_instances(column)
        return np.asarray(
            pc.cast(first, pa.float64()).fill_null(np.nan).to_numpy(zero_copy_only=False), dtype=np.float64
        )
    # Numbers without nulls (the usual case): indexed in numpy, no compute kernels.
    offsets = np.asarray(column.offsets)
    has = offsets[1:] > offsets[:-1]
    if column.null_count:
        has &= np.asarray(column.is_valid(), dtype=bool)
    out = np.full(len(column), np.nan)
    out[has] = values.to_numpy(zero_copy_only=False)[offsets[:-1][has]]
    return out


def first_texts(column: pa.Array) -> list[str | None]:
    """The first instance of each row of a list<string> column (None where the row has none)."""
    first, _ = first_instances(column)
    texts: list[str | None] = first.to_pylist()
    return texts


def vectors(column: pa.Array | None, width: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """First instance of a list<fixed_size_list<float, width>> column as an (n, width) array."""
    if column is None:
        return np.zeros((length, width)), np.zeros(length, dtype=bool)
    first, has = first_instances(column)
    flat = np.asarray(first.values.to_numpy(zero_copy_only=False), dtype=np.float64)
    start = first.offset * width
    return flat[start : start + len(first) * width].reshape(len(first), width), has


def axis_angle_quaternions(column: pa.Array, length: int) -> tuple[np.ndarray, np.ndarray]:
    """First instance of a RotationAxisAngle column as (n, 4) quaternions (x, y, z, w)."""
    first, has = first_instances(column)
    axis = np.asarray(first.field("axis").values.to_numpy(zero_copy_only=False), dtype=np.float64)
    axis = axis.reshape(len(first), 3)
    angle = np.asarray(first.field("angle").to_numpy(zero_copy_only=False), dtype=np.float64)
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    unit = np.divide(axis, norm, out=np.zeros_like(axis), where=norm > 0)
    half = np.nan_to_num(angle) / 2
    quaternion = np.column_stack([unit * np.sin(half)[:, None], np.cos(half)])
    return quaternion, has & (norm[:, 0] > 0)
