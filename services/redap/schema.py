"""A dataset's schema as Rerun's servers answer GetDatasetSchema: each run's Sorbet schema (row id,
timelines, one column per entity and component) in Rerun's column order, merged over the runs.

Rerun orders a recording's columns as its chunk store does: the row id, then the timelines by
name, then the components by entity path (each path part in natural order, "cam2" before "cam10",
case-insensitive first, reserved parts such as `__properties` after every other), archetype,
component and component type. A dataset's schema is Arrow's field-wise merge of its runs' schemas
in turn: a column keeps the place it had in the first run holding it, and gains the metadata of the
others (a column static in one run is marked static)."""

from __future__ import annotations

import functools
import logging
from collections.abc import Iterable

import pyarrow as pa

from services.rrd.fieldmeta import rerun_key

log = logging.getLogger(__name__)

RESERVED_PREFIX = "__"  # entity path parts Rerun keeps to itself, sorted after every other
_CONTROL, _INDEX, _DATA = b"control", b"index", b"data"


def _cmp(a: str | bytes | int, b: str | bytes | int) -> int:
    return int(a > b) - int(a < b)  # type: ignore[operator]


def _is_digit(char: str) -> bool:
    return "0" <= char <= "9"  # ASCII digits only, as Rust's `to_digit(10)`


def _ascii_lower(char: str) -> str:
    return char.lower() if char.isascii() else char


def _digits(text: str, start: int) -> int:
    end = start
    while end < len(text) and _is_digit(text[end]):
        end += 1
    return end


def _compare_numbers(a: str, b: str, leading_zero: bool) -> int:
    """Two runs of digits: as fractions digit by digit when either starts with 0 ("1.02" after
    "1.010"), else as whole numbers (the longer is larger)."""
    if leading_zero:
        for x, y in zip(a, b, strict=False):
            if x != y:
                return _cmp(x, y)
        return _cmp(len(a), len(b))
    return _cmp(len(a), len(b)) or _cmp(a, b)


def natural_compare(a: str, b: str) -> int:
    """Rerun's natural order of strings (the `natord` crate's): numbers by value, letters ignoring
    case first ("a" < "B" < "b")."""
    i = j = 0
    while i < len(a) and j < len(b):
        if _is_digit(a[i]) and _is_digit(b[j]):
            end_a, end_b = _digits(a, i), _digits(b, j)
            found = _compare_numbers(a[i:end_a], b[j:end_b], a[i] == "0" or b[j] == "0")
            if found:
                return found
            i, j = end_a, end_b
            continue
        found = _cmp(_ascii_lower(a[i]), _ascii_lower(b[j])) or _cmp(a[i], b[j])
        if found:
            return found
        i, j = i + 1, j + 1
    return _cmp(len(a) - i, len(b) - j)


def entity_parts(path: str) -> list[str]:
    """The unescaped parts of an entity path (`/world/a\\/b` has two: `world`, `a/b`)."""
    parts, current, escaped = [], [], False
    for char in path:
        if escaped:
            current.append(char)
            escaped = False
        elif char == "\\":
            escaped = True
        elif char == "/":
            parts.append("".join(current))
            current = []
        else:
            current.append(char)
    parts.append("".join(current))
    return [p for p in parts if p]


def _compare_part(a: str, b: str) -> int:
    reserved_a, reserved_b = a.startswith(RESERVED_PREFIX), b.startswith(RESERVED_PREFIX)
    if reserved_a != reserved_b:
        return 1 if reserved_a else -1
    return natural_compare(a, b)


def compare_entity_paths(a: str, b: str) -> int:
    parts_a, parts_b = entity_parts(a), entity_parts(b)
    for x, y in zip(parts_a, parts_b, strict=False):
        found = _compare_part(x, y)
        if found:
            return found
    return _cmp(len(parts_a), len(parts_b))


def _compare_optional(a: bytes | None, b: bytes | None) -> int:
    if a is None or b is None:
        return _cmp(a is not None, b is not None)  # an unset archetype sorts first
    return _cmp(a, b)


def _compare_components(f: pa.Field, g: pa.Field) -> int:
    m, n = f.metadata or {}, g.metadata or {}
    found = compare_entity_paths(rerun_key(m, "entity_path", b"/").decode(), rerun_key(n, "entity_path", b"/").decode())
    for key in ("archetype", "component", "component_type"):
        found = found or _compare_optional(rerun_key(m, key), rerun_key(n, key))
    return found


def _kind(field: pa.Field) -> bytes | None:
    return rerun_key(field, "kind")


def rerun_order(schema: pa.Schema) -> pa.Schema:
    """A recording's Sorbet schema with its columns in the order Rerun's chunk store gives them;
    no schema-level metadata, as Rerun's servers answer."""
    controls = [f for f in schema if _kind(f) == _CONTROL]
    indexes = sorted((f for f in schema if _kind(f) == _INDEX), key=lambda f: f.name)
    components = sorted(
        (f for f in schema if _kind(f) not in (_CONTROL, _INDEX)), key=functools.cmp_to_key(_compare_components)
    )
    return pa.schema(controls + indexes + components)


def _merge_field(first: pa.Field, other: pa.Field) -> pa.Field:
    if first.type != other.type:
        # Rerun's own server refuses to register such a run; the depot already holds both, so the
        # first run's type stands and readers of the others see the difference in their chunks.
        log.warning(
            "column %s is %s in one run and %s in another: kept as %s", first.name, first.type, other.type, first.type
        )
    metadata = {**(other.metadata or {}), **(first.metadata or {})}  # the first value of a key stands
    return first.with_nullable(first.nullable or other.nullable).with_metadata(metadata)


def merge_schemas(schemas: Iterable[pa.Schema]) -> pa.Schema:
    """Arrow's field-wise merge (Rerun's `Schema::try_merge`): fields in first-seen order."""
    fields: dict[str, pa.Field] = {}
    for schema in schemas:
        for field in schema:
            fields[field.name] = _merge_field(fields[field.name], field) if field.name in fields else field
    return pa.schema(list(fields.values()))


def narrowed(schema: pa.Schema, entities: set[str], timelines: set[str]) -> pa.Schema:
    """A run's schema as some of its chunks hold it (a snapshot's episode): the controls, the
    timelines among `timelines`, and the columns of the entities among `entities`."""
    kept = []
    for field in schema:
        kind = _kind(field)
        if kind == _INDEX:
            keep = field.name in timelines
        elif kind == _CONTROL:
            keep = True
        else:
            keep = rerun_key(field, "entity_path", b"/").decode() in entities
        if keep:
            kept.append(field)
    return pa.schema(kept, metadata=schema.metadata)
