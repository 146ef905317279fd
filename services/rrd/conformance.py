"""What Rerun requires of a chunk's schema, checked once per schema (the layout cache keeps the answer).

Found by building malformed chunks and running `rerun rrd verify` (0.41) on them (see
docs/rrd-codec.md, "Chunks Rerun refuses"): Rerun refuses a chunk without a `rerun:id`, without a
`rerun.controls.RowId` column of FixedSizeBinary(16), with an index column that is not
int64/timestamp/duration (already refused by the layout), and a component column whose Arrow type
is not its component's: for the components whose values this server reads (analytics extraction),
the exact list Rerun writes; for every component type Rerun knows (known_components.py), values of
that type, in a list or not. Columns of component types Rerun does not know are its to read.
"""

from __future__ import annotations

import pyarrow as pa

from services.rrd import known_components

CHUNK_ID_KEY = b"rerun:id"
LEGACY_CHUNK_ID_KEY = b"rerun.id"  # SDK 0.23 and older (newer Rerun migrates it)
ROW_ID_TYPE = pa.binary(16)

_F32 = pa.float32()
LIST_F64 = pa.list_(pa.float64())


def _list_of(item: pa.DataType) -> pa.DataType:
    return pa.list_(item)


def _vector(width: int) -> pa.DataType:
    return pa.list_(pa.field("item", _F32, nullable=False), width)


# Component -> the Arrow type Rerun expects of its column (a list per row). Item nullability and
# names are not compared: Rerun accepts either.
READ_COMPONENTS: dict[str, pa.DataType] = {
    "Scalars:scalars": LIST_F64,
    "TextLog:text": _list_of(pa.string()),
    "TextLog:level": _list_of(pa.string()),
    "Transform3D:translation": _list_of(_vector(3)),
    "Transform3D:quaternion": _list_of(_vector(4)),
    "Transform3D:rotation_axis_angle": _list_of(pa.struct([pa.field("axis", _vector(3)), pa.field("angle", _F32)])),
}


def same_type(got: pa.DataType, expected: pa.DataType) -> bool:
    """Equal types, ignoring the names and nullability of nested fields."""
    if got.id != expected.id or got.num_fields != expected.num_fields:
        return False
    if pa.types.is_fixed_size_list(got) and got.list_size != expected.list_size:
        return False
    if pa.types.is_struct(got) and [got.field(i).name for i in range(got.num_fields)] != [
        expected.field(i).name for i in range(expected.num_fields)
    ]:
        return False
    if got.num_fields == 0:
        return bool(got == expected)
    return all(same_type(got.field(i).type, expected.field(i).type) for i in range(got.num_fields))


def component_type_problem(
    component: str, column: str, arrow_type: pa.DataType, component_type: str | None = None
) -> str | None:
    """Why Rerun would refuse this column's type: a component the depot reads must be the list Rerun
    writes; a component type Rerun knows (known_components) must hold values of its type, in a list
    (int32 offsets) or not (Rerun reads any other column as the values themselves)."""
    expected = READ_COMPONENTS.get(component)
    if expected is not None and not same_type(arrow_type, expected):
        return f"column {column!r} ({component}) is {arrow_type}, Rerun expects {expected}"
    value = known_components.expected_type(component_type)
    element = arrow_type.value_type if pa.types.is_list(arrow_type) else arrow_type
    if value is not None and not same_type(element, value):
        return f"column {column!r} ({component_type}) holds {element}, Rerun expects {value} (in a list)"
    return None


def schema_problem(
    schema: pa.Schema, row_id_field: pa.Field | None, data: list[tuple[str, str, pa.DataType, str | None]]
) -> str | None:
    """Why Rerun would refuse chunks of this schema (None: it would not, as far as checked here).
    `data`: (column, component, type, component type) of each data column."""
    metadata = schema.metadata or {}
    if CHUNK_ID_KEY not in metadata and LEGACY_CHUNK_ID_KEY not in metadata:
        return "the Arrow schema has no rerun:id (chunk id) metadata"
    if row_id_field is None:
        return "no rerun.controls.RowId column"
    if row_id_field.type != ROW_ID_TYPE:
        return f"the RowId column is {row_id_field.type}, Rerun expects fixed_size_binary[16]"
    for column, component, arrow_type, component_type in data:
        problem = component_type_problem(component, column, arrow_type, component_type)
        if problem is not None:
            return problem
    return None


def reads_values(component_names: frozenset[str]) -> bool:
    """Whether the server reads the values of chunks holding these components."""
    return not component_names.isdisjoint(READ_COMPONENTS)
