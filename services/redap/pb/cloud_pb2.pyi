import datetime

from google.protobuf import any_pb2 as _any_pb2
from google.protobuf import empty_pb2 as _empty_pb2
from google.protobuf import timestamp_pb2 as _timestamp_pb2
from services.rrd.pb import common_pb2 as _common_pb2
from services.rrd.pb import log_msg_pb2 as _log_msg_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class DataSourceKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DATA_SOURCE_KIND_UNSPECIFIED: _ClassVar[DataSourceKind]
    DATA_SOURCE_KIND_RRD: _ClassVar[DataSourceKind]

class DirectUrlMode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DIRECT_URL_MODE_UNSPECIFIED: _ClassVar[DirectUrlMode]
    DIRECT_URL_MODE_OMIT: _ClassVar[DirectUrlMode]
    DIRECT_URL_MODE_UNSIGNED: _ClassVar[DirectUrlMode]
    DIRECT_URL_MODE_SIGNED: _ClassVar[DirectUrlMode]

class EntryKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ENTRY_KIND_UNSPECIFIED: _ClassVar[EntryKind]
    ENTRY_KIND_DATASET: _ClassVar[EntryKind]
    ENTRY_KIND_DATASET_VIEW: _ClassVar[EntryKind]
    ENTRY_KIND_TABLE: _ClassVar[EntryKind]
    ENTRY_KIND_TABLE_VIEW: _ClassVar[EntryKind]
    ENTRY_KIND_BLUEPRINT_DATASET: _ClassVar[EntryKind]
    ENTRY_KIND_ASSET_DATASET: _ClassVar[EntryKind]

class FillMode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FILL_MODE_UNSPECIFIED: _ClassVar[FillMode]
    FILL_MODE_NONE: _ClassVar[FillMode]
    FILL_MODE_LATEST_AT: _ClassVar[FillMode]
    FILL_MODE_EARLIEST_AT: _ClassVar[FillMode]

class SystemTableKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SYSTEM_TABLE_KIND_UNSPECIFIED: _ClassVar[SystemTableKind]
    SYSTEM_TABLE_KIND_NAMESPACES: _ClassVar[SystemTableKind]
    SYSTEM_TABLE_KIND_ENTRIES: _ClassVar[SystemTableKind]
DATA_SOURCE_KIND_UNSPECIFIED: DataSourceKind
DATA_SOURCE_KIND_RRD: DataSourceKind
DIRECT_URL_MODE_UNSPECIFIED: DirectUrlMode
DIRECT_URL_MODE_OMIT: DirectUrlMode
DIRECT_URL_MODE_UNSIGNED: DirectUrlMode
DIRECT_URL_MODE_SIGNED: DirectUrlMode
ENTRY_KIND_UNSPECIFIED: EntryKind
ENTRY_KIND_DATASET: EntryKind
ENTRY_KIND_DATASET_VIEW: EntryKind
ENTRY_KIND_TABLE: EntryKind
ENTRY_KIND_TABLE_VIEW: EntryKind
ENTRY_KIND_BLUEPRINT_DATASET: EntryKind
ENTRY_KIND_ASSET_DATASET: EntryKind
FILL_MODE_UNSPECIFIED: FillMode
FILL_MODE_NONE: FillMode
FILL_MODE_LATEST_AT: FillMode
FILL_MODE_EARLIEST_AT: FillMode
SYSTEM_TABLE_KIND_UNSPECIFIED: SystemTableKind
SYSTEM_TABLE_KIND_NAMESPACES: SystemTableKind
SYSTEM_TABLE_KIND_ENTRIES: SystemTableKind

class ChunkKey(_message.Message):
    __slots__ = ("chunk_id", "data_source_kind", "location", "etag", "registration_time_nanos")
    CHUNK_ID_FIELD_NUMBER: _ClassVar[int]
    DATA_SOURCE_KIND_FIELD_NUMBER: _ClassVar[int]
    LOCATION_FIELD_NUMBER: _ClassVar[int]
    ETAG_FIELD_NUMBER: _ClassVar[int]
    REGISTRATION_TIME_NANOS_FIELD_NUMBER: _ClassVar[int]
    chunk_id: _common_pb2.Tuid
    data_source_kind: DataSourceKind
    location: bytes
    etag: str
    registration_time_nanos: int
    def __init__(self, chunk_id: _Optional[_Union[_common_pb2.Tuid, _Mapping]] = ..., data_source_kind: _Optional[_Union[DataSourceKind, str]] = ..., location: _Optional[bytes] = ..., etag: _Optional[str] = ..., registration_time_nanos: _Optional[int] = ...) -> None: ...

class ComponentIds(_message.Message):
    __slots__ = ("ids",)
    IDS_FIELD_NUMBER: _ClassVar[int]
    ids: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, ids: _Optional[_Iterable[str]] = ...) -> None: ...

class ContentSelection(_message.Message):
    __slots__ = ("all", "explicit")
    ALL_FIELD_NUMBER: _ClassVar[int]
    EXPLICIT_FIELD_NUMBER: _ClassVar[int]
    all: _empty_pb2.Empty
    explicit: EntitySelections
    def __init__(self, all: _Optional[_Union[_empty_pb2.Empty, _Mapping]] = ..., explicit: _Optional[_Union[EntitySelections, _Mapping]] = ...) -> None: ...

class DatasetDetails(_message.Message):
    __slots__ = ("blueprint_dataset", "default_blueprint_segment", "default_segment_table_blueprint_segment", "asset_dataset")
    BLUEPRINT_DATASET_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_BLUEPRINT_SEGMENT_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_SEGMENT_TABLE_BLUEPRINT_SEGMENT_FIELD_NUMBER: _ClassVar[int]
    ASSET_DATASET_FIELD_NUMBER: _ClassVar[int]
    blueprint_dataset: _common_pb2.EntryId
    default_blueprint_segment: _common_pb2.SegmentId
    default_segment_table_blueprint_segment: _common_pb2.SegmentId
    asset_dataset: _common_pb2.EntryId
    def __init__(self, blueprint_dataset: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ..., default_blueprint_segment: _Optional[_Union[_common_pb2.SegmentId, _Mapping]] = ..., default_segment_table_blueprint_segment: _Optional[_Union[_common_pb2.SegmentId, _Mapping]] = ..., asset_dataset: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ...) -> None: ...

class DatasetEntry(_message.Message):
    __slots__ = ("details", "dataset_details", "dataset_handle")
    DETAILS_FIELD_NUMBER: _ClassVar[int]
    DATASET_DETAILS_FIELD_NUMBER: _ClassVar[int]
    DATASET_HANDLE_FIELD_NUMBER: _ClassVar[int]
    details: EntryDetails
    dataset_details: DatasetDetails
    dataset_handle: _common_pb2.DatasetHandle
    def __init__(self, details: _Optional[_Union[EntryDetails, _Mapping]] = ..., dataset_details: _Optional[_Union[DatasetDetails, _Mapping]] = ..., dataset_handle: _Optional[_Union[_common_pb2.DatasetHandle, _Mapping]] = ...) -> None: ...

class DatasetResponseMeta(_message.Message):
    __slots__ = ("entry_id", "dataset_revision")
    ENTRY_ID_FIELD_NUMBER: _ClassVar[int]
    DATASET_REVISION_FIELD_NUMBER: _ClassVar[int]
    entry_id: _common_pb2.EntryId
    dataset_revision: int
    def __init__(self, entry_id: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ..., dataset_revision: _Optional[int] = ...) -> None: ...

class EntitySelection(_message.Message):
    __slots__ = ("entity_path", "all", "explicit")
    ENTITY_PATH_FIELD_NUMBER: _ClassVar[int]
    ALL_FIELD_NUMBER: _ClassVar[int]
    EXPLICIT_FIELD_NUMBER: _ClassVar[int]
    entity_path: _common_pb2.EntityPath
    all: _empty_pb2.Empty
    explicit: ComponentIds
    def __init__(self, entity_path: _Optional[_Union[_common_pb2.EntityPath, _Mapping]] = ..., all: _Optional[_Union[_empty_pb2.Empty, _Mapping]] = ..., explicit: _Optional[_Union[ComponentIds, _Mapping]] = ...) -> None: ...

class EntitySelections(_message.Message):
    __slots__ = ("entities",)
    ENTITIES_FIELD_NUMBER: _ClassVar[int]
    entities: _containers.RepeatedCompositeFieldContainer[EntitySelection]
    def __init__(self, entities: _Optional[_Iterable[_Union[EntitySelection, _Mapping]]] = ...) -> None: ...

class EntryDetails(_message.Message):
    __slots__ = ("id", "name", "entry_kind", "created_at", "updated_at")
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ENTRY_KIND_FIELD_NUMBER: _ClassVar[int]
    CREATED_AT_FIELD_NUMBER: _ClassVar[int]
    UPDATED_AT_FIELD_NUMBER: _ClassVar[int]
    id: _common_pb2.EntryId
    name: str
    entry_kind: EntryKind
    created_at: _timestamp_pb2.Timestamp
    updated_at: _timestamp_pb2.Timestamp
    def __init__(self, id: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ..., name: _Optional[str] = ..., entry_kind: _Optional[_Union[EntryKind, str]] = ..., created_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., updated_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class EntryFilter(_message.Message):
    __slots__ = ("id", "name", "entry_kind", "entry_kinds")
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ENTRY_KIND_FIELD_NUMBER: _ClassVar[int]
    ENTRY_KINDS_FIELD_NUMBER: _ClassVar[int]
    id: _common_pb2.EntryId
    name: str
    entry_kind: EntryKind
    entry_kinds: _containers.RepeatedScalarFieldContainer[EntryKind]
    def __init__(self, id: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ..., name: _Optional[str] = ..., entry_kind: _Optional[_Union[EntryKind, str]] = ..., entry_kinds: _Optional[_Iterable[_Union[EntryKind, str]]] = ...) -> None: ...

class FetchChunksRequest(_message.Message):
    __slots__ = ("chunk_infos",)
    CHUNK_INFOS_FIELD_NUMBER: _ClassVar[int]
    chunk_infos: _containers.RepeatedCompositeFieldContainer[_common_pb2.DataframePart]
    def __init__(self, chunk_infos: _Optional[_Iterable[_Union[_common_pb2.DataframePart, _Mapping]]] = ...) -> None: ...

class FetchChunksResponse(_message.Message):
    __slots__ = ("chunks",)
    CHUNKS_FIELD_NUMBER: _ClassVar[int]
    chunks: _containers.RepeatedCompositeFieldContainer[_log_msg_pb2.ArrowMsg]
    def __init__(self, chunks: _Optional[_Iterable[_Union[_log_msg_pb2.ArrowMsg, _Mapping]]] = ...) -> None: ...

class FindChunksRequest(_message.Message):
    __slots__ = ("contents", "static", "range", "samples", "direct_url_mode")
    CONTENTS_FIELD_NUMBER: _ClassVar[int]
    STATIC_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    DIRECT_URL_MODE_FIELD_NUMBER: _ClassVar[int]
    contents: ContentSelection
    static: StaticSelection
    range: RangeSelection
    samples: SegmentSamplesSelection
    direct_url_mode: DirectUrlMode
    def __init__(self, contents: _Optional[_Union[ContentSelection, _Mapping]] = ..., static: _Optional[_Union[StaticSelection, _Mapping]] = ..., range: _Optional[_Union[RangeSelection, _Mapping]] = ..., samples: _Optional[_Union[SegmentSamplesSelection, _Mapping]] = ..., direct_url_mode: _Optional[_Union[DirectUrlMode, str]] = ...) -> None: ...

class FindChunksResponse(_message.Message):
    __slots__ = ("data", "meta")
    DATA_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    data: _common_pb2.DataframePart
    meta: DatasetResponseMeta
    def __init__(self, data: _Optional[_Union[_common_pb2.DataframePart, _Mapping]] = ..., meta: _Optional[_Union[DatasetResponseMeta, _Mapping]] = ...) -> None: ...

class FindEntriesRequest(_message.Message):
    __slots__ = ("filter",)
    FILTER_FIELD_NUMBER: _ClassVar[int]
    filter: EntryFilter
    def __init__(self, filter: _Optional[_Union[EntryFilter, _Mapping]] = ...) -> None: ...

class FindEntriesResponse(_message.Message):
    __slots__ = ("entries",)
    ENTRIES_FIELD_NUMBER: _ClassVar[int]
    entries: _containers.RepeatedCompositeFieldContainer[EntryDetails]
    def __init__(self, entries: _Optional[_Iterable[_Union[EntryDetails, _Mapping]]] = ...) -> None: ...

class GetAssetsForSegmentRequest(_message.Message):
    __slots__ = ("segment_id",)
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    segment_id: _common_pb2.SegmentId
    def __init__(self, segment_id: _Optional[_Union[_common_pb2.SegmentId, _Mapping]] = ...) -> None: ...

class GetAssetsForSegmentResponse(_message.Message):
    __slots__ = ("assets_entry", "asset_segment_ids")
    ASSETS_ENTRY_FIELD_NUMBER: _ClassVar[int]
    ASSET_SEGMENT_IDS_FIELD_NUMBER: _ClassVar[int]
    assets_entry: _common_pb2.EntryId
    asset_segment_ids: _containers.RepeatedCompositeFieldContainer[_common_pb2.SegmentId]
    def __init__(self, assets_entry: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ..., asset_segment_ids: _Optional[_Iterable[_Union[_common_pb2.SegmentId, _Mapping]]] = ...) -> None: ...

class GetDatasetSchemaRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GetDatasetSchemaResponse(_message.Message):
    __slots__ = ("schema", "meta")
    SCHEMA_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    schema: _common_pb2.Schema
    meta: DatasetResponseMeta
    def __init__(self, schema: _Optional[_Union[_common_pb2.Schema, _Mapping]] = ..., meta: _Optional[_Union[DatasetResponseMeta, _Mapping]] = ...) -> None: ...

class GetRrdManifestRequest(_message.Message):
    __slots__ = ("segment_id", "generate_direct_urls")
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    GENERATE_DIRECT_URLS_FIELD_NUMBER: _ClassVar[int]
    segment_id: _common_pb2.SegmentId
    generate_direct_urls: bool
    def __init__(self, segment_id: _Optional[_Union[_common_pb2.SegmentId, _Mapping]] = ..., generate_direct_urls: _Optional[bool] = ...) -> None: ...

class GetRrdManifestResponse(_message.Message):
    __slots__ = ("rrd_manifest", "manifest_key", "meta")
    RRD_MANIFEST_FIELD_NUMBER: _ClassVar[int]
    MANIFEST_KEY_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    rrd_manifest: _log_msg_pb2.RrdManifest
    manifest_key: RrdManifestKey
    meta: DatasetResponseMeta
    def __init__(self, rrd_manifest: _Optional[_Union[_log_msg_pb2.RrdManifest, _Mapping]] = ..., manifest_key: _Optional[_Union[RrdManifestKey, _Mapping]] = ..., meta: _Optional[_Union[DatasetResponseMeta, _Mapping]] = ...) -> None: ...

class GetSegmentTableSchemaRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GetSegmentTableSchemaResponse(_message.Message):
    __slots__ = ("schema", "meta")
    SCHEMA_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    schema: _common_pb2.Schema
    meta: DatasetResponseMeta
    def __init__(self, schema: _Optional[_Union[_common_pb2.Schema, _Mapping]] = ..., meta: _Optional[_Union[DatasetResponseMeta, _Mapping]] = ...) -> None: ...

class GetTableSchemaRequest(_message.Message):
    __slots__ = ("table_id",)
    TABLE_ID_FIELD_NUMBER: _ClassVar[int]
    table_id: _common_pb2.EntryId
    def __init__(self, table_id: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ...) -> None: ...

class GetTableSchemaResponse(_message.Message):
    __slots__ = ("schema",)
    SCHEMA_FIELD_NUMBER: _ClassVar[int]
    schema: _common_pb2.Schema
    def __init__(self, schema: _Optional[_Union[_common_pb2.Schema, _Mapping]] = ...) -> None: ...

class IndexValueList(_message.Message):
    __slots__ = ("values",)
    VALUES_FIELD_NUMBER: _ClassVar[int]
    values: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, values: _Optional[_Iterable[int]] = ...) -> None: ...

class Query(_message.Message):
    __slots__ = ("latest_at", "range", "columns_always_include_everything", "columns_always_include_byte_offsets", "columns_always_include_entity_paths", "columns_always_include_static_indexes", "columns_always_include_global_indexes", "columns_always_include_component_indexes")
    LATEST_AT_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_ALWAYS_INCLUDE_EVERYTHING_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_ALWAYS_INCLUDE_BYTE_OFFSETS_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_ALWAYS_INCLUDE_ENTITY_PATHS_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_ALWAYS_INCLUDE_STATIC_INDEXES_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_ALWAYS_INCLUDE_GLOBAL_INDEXES_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_ALWAYS_INCLUDE_COMPONENT_INDEXES_FIELD_NUMBER: _ClassVar[int]
    latest_at: QueryLatestAt
    range: QueryRange
    columns_always_include_everything: bool
    columns_always_include_byte_offsets: bool
    columns_always_include_entity_paths: bool
    columns_always_include_static_indexes: bool
    columns_always_include_global_indexes: bool
    columns_always_include_component_indexes: bool
    def __init__(self, latest_at: _Optional[_Union[QueryLatestAt, _Mapping]] = ..., range: _Optional[_Union[QueryRange, _Mapping]] = ..., columns_always_include_everything: _Optional[bool] = ..., columns_always_include_byte_offsets: _Optional[bool] = ..., columns_always_include_entity_paths: _Optional[bool] = ..., columns_always_include_static_indexes: _Optional[bool] = ..., columns_always_include_global_indexes: _Optional[bool] = ..., columns_always_include_component_indexes: _Optional[bool] = ...) -> None: ...

class QueryDatasetRequest(_message.Message):
    __slots__ = ("segment_ids", "generate_direct_urls", "unsigned_direct_urls", "chunk_ids", "entity_paths", "select_all_entity_paths", "fuzzy_descriptors", "exclude_static_data", "exclude_temporal_data", "scan_parameters", "query")
    SEGMENT_IDS_FIELD_NUMBER: _ClassVar[int]
    GENERATE_DIRECT_URLS_FIELD_NUMBER: _ClassVar[int]
    UNSIGNED_DIRECT_URLS_FIELD_NUMBER: _ClassVar[int]
    CHUNK_IDS_FIELD_NUMBER: _ClassVar[int]
    ENTITY_PATHS_FIELD_NUMBER: _ClassVar[int]
    SELECT_ALL_ENTITY_PATHS_FIELD_NUMBER: _ClassVar[int]
    FUZZY_DESCRIPTORS_FIELD_NUMBER: _ClassVar[int]
    EXCLUDE_STATIC_DATA_FIELD_NUMBER: _ClassVar[int]
    EXCLUDE_TEMPORAL_DATA_FIELD_NUMBER: _ClassVar[int]
    SCAN_PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    QUERY_FIELD_NUMBER: _ClassVar[int]
    segment_ids: _containers.RepeatedCompositeFieldContainer[_common_pb2.SegmentId]
    generate_direct_urls: bool
    unsigned_direct_urls: bool
    chunk_ids: _containers.RepeatedCompositeFieldContainer[_common_pb2.Tuid]
    entity_paths: _containers.RepeatedCompositeFieldContainer[_common_pb2.EntityPath]
    select_all_entity_paths: bool
    fuzzy_descriptors: _containers.RepeatedScalarFieldContainer[str]
    exclude_static_data: bool
    exclude_temporal_data: bool
    scan_parameters: _common_pb2.ScanParameters
    query: Query
    def __init__(self, segment_ids: _Optional[_Iterable[_Union[_common_pb2.SegmentId, _Mapping]]] = ..., generate_direct_urls: _Optional[bool] = ..., unsigned_direct_urls: _Optional[bool] = ..., chunk_ids: _Optional[_Iterable[_Union[_common_pb2.Tuid, _Mapping]]] = ..., entity_paths: _Optional[_Iterable[_Union[_common_pb2.EntityPath, _Mapping]]] = ..., select_all_entity_paths: _Optional[bool] = ..., fuzzy_descriptors: _Optional[_Iterable[str]] = ..., exclude_static_data: _Optional[bool] = ..., exclude_temporal_data: _Optional[bool] = ..., scan_parameters: _Optional[_Union[_common_pb2.ScanParameters, _Mapping]] = ..., query: _Optional[_Union[Query, _Mapping]] = ...) -> None: ...

class QueryDatasetResponse(_message.Message):
    __slots__ = ("data", "meta")
    DATA_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    data: _common_pb2.DataframePart
    meta: DatasetResponseMeta
    def __init__(self, data: _Optional[_Union[_common_pb2.DataframePart, _Mapping]] = ..., meta: _Optional[_Union[DatasetResponseMeta, _Mapping]] = ...) -> None: ...

class QueryLatestAt(_message.Message):
    __slots__ = ("index", "at", "per_segment_values")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    AT_FIELD_NUMBER: _ClassVar[int]
    PER_SEGMENT_VALUES_FIELD_NUMBER: _ClassVar[int]
    index: _common_pb2.IndexColumnSelector
    at: int
    per_segment_values: _containers.RepeatedCompositeFieldContainer[IndexValueList]
    def __init__(self, index: _Optional[_Union[_common_pb2.IndexColumnSelector, _Mapping]] = ..., at: _Optional[int] = ..., per_segment_values: _Optional[_Iterable[_Union[IndexValueList, _Mapping]]] = ...) -> None: ...

class QueryRange(_message.Message):
    __slots__ = ("index", "index_range")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    INDEX_RANGE_FIELD_NUMBER: _ClassVar[int]
    index: _common_pb2.IndexColumnSelector
    index_range: _common_pb2.TimeRange
    def __init__(self, index: _Optional[_Union[_common_pb2.IndexColumnSelector, _Mapping]] = ..., index_range: _Optional[_Union[_common_pb2.TimeRange, _Mapping]] = ...) -> None: ...

class RangeSelection(_message.Message):
    __slots__ = ("timeline", "start_inclusive", "end_inclusive", "fill_mode", "segments")
    TIMELINE_FIELD_NUMBER: _ClassVar[int]
    START_INCLUSIVE_FIELD_NUMBER: _ClassVar[int]
    END_INCLUSIVE_FIELD_NUMBER: _ClassVar[int]
    FILL_MODE_FIELD_NUMBER: _ClassVar[int]
    SEGMENTS_FIELD_NUMBER: _ClassVar[int]
    timeline: str
    start_inclusive: int
    end_inclusive: int
    fill_mode: FillMode
    segments: SegmentSelection
    def __init__(self, timeline: _Optional[str] = ..., start_inclusive: _Optional[int] = ..., end_inclusive: _Optional[int] = ..., fill_mode: _Optional[_Union[FillMode, str]] = ..., segments: _Optional[_Union[SegmentSelection, _Mapping]] = ...) -> None: ...

class ReadDatasetEntryRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ReadDatasetEntryResponse(_message.Message):
    __slots__ = ("dataset",)
    DATASET_FIELD_NUMBER: _ClassVar[int]
    dataset: DatasetEntry
    def __init__(self, dataset: _Optional[_Union[DatasetEntry, _Mapping]] = ...) -> None: ...

class ReadTableEntryRequest(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: _common_pb2.EntryId
    def __init__(self, id: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ...) -> None: ...

class ReadTableEntryResponse(_message.Message):
    __slots__ = ("table",)
    TABLE_FIELD_NUMBER: _ClassVar[int]
    table: TableEntry
    def __init__(self, table: _Optional[_Union[TableEntry, _Mapping]] = ...) -> None: ...

class RrdChunkLocation(_message.Message):
    __slots__ = ("url", "offset", "length", "object_store_config")
    URL_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    LENGTH_FIELD_NUMBER: _ClassVar[int]
    OBJECT_STORE_CONFIG_FIELD_NUMBER: _ClassVar[int]
    url: str
    offset: int
    length: int
    object_store_config: str
    def __init__(self, url: _Optional[str] = ..., offset: _Optional[int] = ..., length: _Optional[int] = ..., object_store_config: _Optional[str] = ...) -> None: ...

class RrdManifestKey(_message.Message):
    __slots__ = ("location", "layer", "etag", "direct_url")
    LOCATION_FIELD_NUMBER: _ClassVar[int]
    LAYER_FIELD_NUMBER: _ClassVar[int]
    ETAG_FIELD_NUMBER: _ClassVar[int]
    DIRECT_URL_FIELD_NUMBER: _ClassVar[int]
    location: RrdChunkLocation
    layer: str
    etag: str
    direct_url: str
    def __init__(self, location: _Optional[_Union[RrdChunkLocation, _Mapping]] = ..., layer: _Optional[str] = ..., etag: _Optional[str] = ..., direct_url: _Optional[str] = ...) -> None: ...

class ScanSegmentTableRequest(_message.Message):
    __slots__ = ("columns", "segment_id_filter")
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_ID_FILTER_FIELD_NUMBER: _ClassVar[int]
    columns: _containers.RepeatedScalarFieldContainer[str]
    segment_id_filter: SegmentIdFilter
    def __init__(self, columns: _Optional[_Iterable[str]] = ..., segment_id_filter: _Optional[_Union[SegmentIdFilter, _Mapping]] = ...) -> None: ...

class ScanSegmentTableResponse(_message.Message):
    __slots__ = ("data", "meta")
    DATA_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    data: _common_pb2.DataframePart
    meta: DatasetResponseMeta
    def __init__(self, data: _Optional[_Union[_common_pb2.DataframePart, _Mapping]] = ..., meta: _Optional[_Union[DatasetResponseMeta, _Mapping]] = ...) -> None: ...

class ScanTableRequest(_message.Message):
    __slots__ = ("table_id",)
    TABLE_ID_FIELD_NUMBER: _ClassVar[int]
    table_id: _common_pb2.EntryId
    def __init__(self, table_id: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ...) -> None: ...

class ScanTableResponse(_message.Message):
    __slots__ = ("dataframe_part",)
    DATAFRAME_PART_FIELD_NUMBER: _ClassVar[int]
    dataframe_part: _common_pb2.DataframePart
    def __init__(self, dataframe_part: _Optional[_Union[_common_pb2.DataframePart, _Mapping]] = ...) -> None: ...

class SegmentIdFilter(_message.Message):
    __slots__ = ("scan_only", "skip")
    SCAN_ONLY_FIELD_NUMBER: _ClassVar[int]
    SKIP_FIELD_NUMBER: _ClassVar[int]
    scan_only: SegmentIdList
    skip: SegmentIdList
    def __init__(self, scan_only: _Optional[_Union[SegmentIdList, _Mapping]] = ..., skip: _Optional[_Union[SegmentIdList, _Mapping]] = ...) -> None: ...

class SegmentIdList(_message.Message):
    __slots__ = ("segment_ids",)
    SEGMENT_IDS_FIELD_NUMBER: _ClassVar[int]
    segment_ids: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, segment_ids: _Optional[_Iterable[str]] = ...) -> None: ...

class SegmentIds(_message.Message):
    __slots__ = ("ids",)
    IDS_FIELD_NUMBER: _ClassVar[int]
    ids: _containers.RepeatedCompositeFieldContainer[_common_pb2.SegmentId]
    def __init__(self, ids: _Optional[_Iterable[_Union[_common_pb2.SegmentId, _Mapping]]] = ...) -> None: ...

class SegmentSamples(_message.Message):
    __slots__ = ("segment_id", "values")
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    segment_id: _common_pb2.SegmentId
    values: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, segment_id: _Optional[_Union[_common_pb2.SegmentId, _Mapping]] = ..., values: _Optional[_Iterable[int]] = ...) -> None: ...

class SegmentSamplesSelection(_message.Message):
    __slots__ = ("timeline", "segments", "fill_mode")
    TIMELINE_FIELD_NUMBER: _ClassVar[int]
    SEGMENTS_FIELD_NUMBER: _ClassVar[int]
    FILL_MODE_FIELD_NUMBER: _ClassVar[int]
    timeline: str
    segments: _containers.RepeatedCompositeFieldContainer[SegmentSamples]
    fill_mode: FillMode
    def __init__(self, timeline: _Optional[str] = ..., segments: _Optional[_Iterable[_Union[SegmentSamples, _Mapping]]] = ..., fill_mode: _Optional[_Union[FillMode, str]] = ...) -> None: ...

class SegmentSelection(_message.Message):
    __slots__ = ("all", "explicit")
    ALL_FIELD_NUMBER: _ClassVar[int]
    EXPLICIT_FIELD_NUMBER: _ClassVar[int]
    all: _empty_pb2.Empty
    explicit: SegmentIds
    def __init__(self, all: _Optional[_Union[_empty_pb2.Empty, _Mapping]] = ..., explicit: _Optional[_Union[SegmentIds, _Mapping]] = ...) -> None: ...

class ServerCapabilities(_message.Message):
    __slots__ = ("capabilities",)
    CAPABILITIES_FIELD_NUMBER: _ClassVar[int]
    capabilities: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, capabilities: _Optional[_Iterable[str]] = ...) -> None: ...

class StaticSelection(_message.Message):
    __slots__ = ("segments",)
    SEGMENTS_FIELD_NUMBER: _ClassVar[int]
    segments: SegmentSelection
    def __init__(self, segments: _Optional[_Union[SegmentSelection, _Mapping]] = ...) -> None: ...

class SystemTable(_message.Message):
    __slots__ = ("kind",)
    KIND_FIELD_NUMBER: _ClassVar[int]
    kind: SystemTableKind
    def __init__(self, kind: _Optional[_Union[SystemTableKind, str]] = ...) -> None: ...

class TableDetails(_message.Message):
    __slots__ = ("blueprint_dataset", "default_blueprint_segment")
    BLUEPRINT_DATASET_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_BLUEPRINT_SEGMENT_FIELD_NUMBER: _ClassVar[int]
    blueprint_dataset: _common_pb2.EntryId
    default_blueprint_segment: _common_pb2.SegmentId
    def __init__(self, blueprint_dataset: _Optional[_Union[_common_pb2.EntryId, _Mapping]] = ..., default_blueprint_segment: _Optional[_Union[_common_pb2.SegmentId, _Mapping]] = ...) -> None: ...

class TableEntry(_message.Message):
    __slots__ = ("details", "provider_details", "table_details")
    DETAILS_FIELD_NUMBER: _ClassVar[int]
    PROVIDER_DETAILS_FIELD_NUMBER: _ClassVar[int]
    TABLE_DETAILS_FIELD_NUMBER: _ClassVar[int]
    details: EntryDetails
    provider_details: _any_pb2.Any
    table_details: TableDetails
    def __init__(self, details: _Optional[_Union[EntryDetails, _Mapping]] = ..., provider_details: _Optional[_Union[_any_pb2.Any, _Mapping]] = ..., table_details: _Optional[_Union[TableDetails, _Mapping]] = ...) -> None: ...

class VersionRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class VersionResponse(_message.Message):
    __slots__ = ("build_info", "version", "cloud_provider", "cloud_region", "features")
    BUILD_INFO_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    CLOUD_PROVIDER_FIELD_NUMBER: _ClassVar[int]
    CLOUD_REGION_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    build_info: _common_pb2.BuildInfo
    version: str
    cloud_provider: str
    cloud_region: str
    features: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, build_info: _Optional[_Union[_common_pb2.BuildInfo, _Mapping]] = ..., version: _Optional[str] = ..., cloud_provider: _Optional[str] = ..., cloud_region: _Optional[str] = ..., features: _Optional[_Iterable[str]] = ...) -> None: ...

class WhoAmIRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class WhoAmIResponse(_message.Message):
    __slots__ = ("user_id", "can_read", "can_write", "capabilities")
    USER_ID_FIELD_NUMBER: _ClassVar[int]
    CAN_READ_FIELD_NUMBER: _ClassVar[int]
    CAN_WRITE_FIELD_NUMBER: _ClassVar[int]
    CAPABILITIES_FIELD_NUMBER: _ClassVar[int]
    user_id: str
    can_read: bool
    can_write: bool
    capabilities: ServerCapabilities
    def __init__(self, user_id: _Optional[str] = ..., can_read: _Optional[bool] = ..., can_write: _Optional[bool] = ..., capabilities: _Optional[_Union[ServerCapabilities, _Mapping]] = ...) -> None: ...
