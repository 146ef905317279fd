"""Chunk column descriptors as the reading Rerun sees them: Rerun's Sorbet migrations, for metadata.

Newer Rerun migrates the schema of every chunk an older SDK wrote before using it (re_sorbet's
migrations, chosen by the chunk's `sorbet:version`, guessed when absent), and names the RRD
manifest's and the Sorbet schema's columns after the *migrated* descriptors. A footer that
names them after the descriptors as written is refused by `rerun rrd verify` and `rerun server`
(`static index 'TransformAxes3D:axis_length:has_static_data' is missing`). This applies the same
renames to the metadata only; chunk payload bytes are never changed.

Sorbet versions: 0.0.1 = SDK 0.23 and older ("rerun." keys), 0.1.1 = SDK 0.24-0.27,
0.1.2 = 0.28 on; migrations in order:
  0.0.2  archetypes Scalar/SeriesLine/SeriesPoint -> Scalars/SeriesLines/SeriesPoints (and fields)
  0.1.0  "rerun.x" keys -> "rerun:x"; (archetype, archetype_field, component) -> archetype,
         "Archetype:field" component and component_type; RecordingProperties -> RecordingInfo,
         /__properties/recording -> /__properties
  0.1.1  indicator columns dropped
  0.1.2  Pose* component types -> Translation3D, RotationQuat, ...; Transform3D:axis_length ->
         TransformAxes3D:axis_length; CoordinateFrame:frame_id -> CoordinateFrame:frame
  0.1.3  component type SeriesVisible -> Visible
  0.1.4  blueprint TableColumn:cell_kind (TableCellKind) -> TableColumn:column_type (ColumnType)
Sorbet versions to 0.1.3 follow re_sorbet's source; 0.1.4 (Rerun 0.37-0.41) follows what the
pinned Rerun's own migration reports.
"""

from __future__ import annotations

SorbetVersion = tuple[int, int, int]

VERSION_KEY = b"sorbet:version"
CURRENT_VERSION: SorbetVersion = (0, 1, 4)  # what the pinned rerun-sdk 0.41 writes
_LEGACY_PREFIX = b"rerun."
_PROPERTIES_RECORDING = b"/__properties/recording"

ARCHETYPE = b"rerun:archetype"
COMPONENT = b"rerun:component"
COMPONENT_TYPE = b"rerun:component_type"
ENTITY_PATH = b"rerun:entity_path"

# 0.0.2: (archetype -> new archetype, {field -> new field})
_ARCHETYPE_RENAMES: dict[bytes, tuple[bytes, dict[bytes, bytes]]] = {
    b"rerun.archetypes.Scalar": (b"rerun.archetypes.Scalars", {b"scalar": b"scalars"}),
    b"rerun.archetypes.SeriesLine": (
        b"rerun.archetypes.SeriesLines",
        {b"color": b"colors", b"width": b"widths", b"name": b"names"},
    ),
    b"rerun.archetypes.SeriesPoint": (
        b"rerun.archetypes.SeriesPoints",
        {b"color": b"colors", b"marker": b"markers", b"name": b"names", b"marker_size": b"marker_sizes"},
    ),
}
# 0.1.2 and 0.1.3: component types
_COMPONENT_TYPE_RENAMES: list[tuple[SorbetVersion, dict[bytes, bytes]]] = [
    (
        (0, 1, 2),
        {
            b"rerun.components.PoseTranslation3D": b"rerun.components.Translation3D",
            b"rerun.components.PoseRotationAxisAngle": b"rerun.components.RotationAxisAngle",
            b"rerun.components.PoseRotationQuat": b"rerun.components.RotationQuat",
            b"rerun.components.PoseScale3D": b"rerun.components.Scale3D",
            b"rerun.components.PoseTransformMat3x3": b"rerun.components.TransformMat3x3",
        },
    ),
    ((0, 1, 3), {b"rerun.components.SeriesVisible": b"rerun.components.Visible"}),
    ((0, 1, 4), {b"rerun.blueprint.components.TableCellKind": b"rerun.blueprint.components.ColumnType"}),
]
# components, with the archetype they move to (None: the archetype stays), by target version
_COMPONENT_RENAMES: list[tuple[SorbetVersion, dict[bytes, tuple[bytes, bytes | None]]]] = [
    (
        (0, 1, 2),
        {
            b"Transform3D:axis_length": (b"TransformAxes3D:axis_length", b"rerun.archetypes.TransformAxes3D"),
            b"CoordinateFrame:frame_id": (b"CoordinateFrame:frame", None),
        },
    ),
    ((0, 1, 4), {b"TableColumn:cell_kind": (b"TableColumn:column_type", None)}),
]


def sorbet_version(schema_metadata: dict[bytes, bytes]) -> SorbetVersion:
    """The chunk's Sorbet version, guessed as Rerun guesses it when the chunk does not say."""
    raw = schema_metadata.get(VERSION_KEY)
    if raw is None:
        if any(k.startswith(_LEGACY_PREFIX) for k in schema_metadata):
            return (0, 0, 1)  # SDK 0.23 and older
        return (0, 0, 2) if b"rerun:version" in schema_metadata else (0, 0, 1)
    try:
        parts = raw.decode().split("-", 1)[0].split("+", 1)[0].split(".")
        major, minor, patch = (int(p) for p in parts)
    except (UnicodeDecodeError, ValueError):
        return CURRENT_VERSION  # Rerun skips migrations of a version it cannot parse
    return (major, minor, patch)


def migrate_schema_metadata(md: dict[bytes, bytes], version: SorbetVersion) -> dict[bytes, bytes]:
    """Chunk-level metadata (entity path, chunk id...) under the keys and values Rerun reads."""
    if version >= (0, 1, 0):
        return md
    out = {_colon_key(k): v for k, v in md.items() if k != b"rerun.version"}
    if out.get(ENTITY_PATH) == _PROPERTIES_RECORDING:
        out[ENTITY_PATH] = b"/__properties"
    return out


def migrate_field_metadata(name: str, md: dict[bytes, bytes], version: SorbetVersion) -> dict[bytes, bytes] | None:
    """A column's metadata as Rerun sees it after migrating from `version`; None when Rerun drops
    the column (indicators)."""
    if version >= CURRENT_VERSION:
        return md
    md = dict(md)
    if version < (0, 0, 2):
        _rename_archetype(md)
    if version < (0, 1, 0):
        md = _to_tagged_descriptor(name, md)
    if version < (0, 1, 1) and _is_indicator(md):
        return None
    for target, renames in _COMPONENT_TYPE_RENAMES:
        component_type = md.get(COMPONENT_TYPE)
        if version < target and component_type in renames:
            md[COMPONENT_TYPE] = renames[component_type]
    for target, component_renames in _COMPONENT_RENAMES:
        rename = component_renames.get(md.get(COMPONENT, b""))
        if version < target and rename is not None:
            md[COMPONENT] = rename[0]
            if rename[1] is not None:
                md[ARCHETYPE] = rename[1]
    return md


def _colon_key(key: bytes) -> bytes:
    return b"rerun:" + key[len(_LEGACY_PREFIX) :] if key.startswith(_LEGACY_PREFIX) else key


def _rename_archetype(md: dict[bytes, bytes]) -> None:
    rename = _ARCHETYPE_RENAMES.get(md.get(b"rerun.archetype", b""))
    if rename is None:
        return
    md[b"rerun.archetype"] = rename[0]
    field_name = md.get(b"rerun.archetype_field")
    if field_name is not None and field_name in rename[1]:
        md[b"rerun.archetype_field"] = rename[1][field_name]


def _to_tagged_descriptor(name: str, md: dict[bytes, bytes]) -> dict[bytes, bytes]:
    """0.1.0: (archetype, archetype_field, component type) -> archetype, `Short:field`, type."""
    archetype = md.pop(b"rerun.archetype", None)
    archetype_field = md.pop(b"rerun.archetype_field", None)
    legacy_component = md.pop(b"rerun.component", None)
    out = {_colon_key(k): v for k, v in md.items()}
    if name.endswith("Indicator"):
        if legacy_component is not None:
            out[COMPONENT] = legacy_component
        else:
            out[COMPONENT] = name.encode() if name.startswith("rerun.") else b"rerun.components." + name.encode()
    elif legacy_component is not None:
        if archetype is None:
            out[COMPONENT] = archetype_field or legacy_component
            if archetype_field is not None:
                out[COMPONENT_TYPE] = legacy_component
        elif archetype_field is not None:
            short = archetype.removeprefix(b"rerun.archetypes.").removeprefix(b"rerun.blueprint.archetypes.")
            out[ARCHETYPE] = archetype
            out[COMPONENT] = short.strip() + b":" + archetype_field
            out[COMPONENT_TYPE] = legacy_component
        elif legacy_component.endswith(b"Indicator"):
            out[COMPONENT] = legacy_component
        else:
            out[ARCHETYPE], out[COMPONENT], out[COMPONENT_TYPE] = archetype, legacy_component, legacy_component
    # RecordingProperties became RecordingInfo, moved from /__properties/recording to /__properties.
    out = {k: v.replace(b"RecordingProperties", b"RecordingInfo") for k, v in out.items()}
    if out.get(ENTITY_PATH) == _PROPERTIES_RECORDING:
        out[ENTITY_PATH] = b"/__properties"
    return out


def _is_indicator(md: dict[bytes, bytes]) -> bool:
    flag = md.get(b"rerun:is_indicator")
    if flag is not None:
        return flag == b"true"
    component = md.get(COMPONENT, b"")
    return component.startswith(b"rerun.components.") and component.endswith(b"Indicator")
