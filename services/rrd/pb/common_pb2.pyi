from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class StoreKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STORE_KIND_UNSPECIFIED: _ClassVar[StoreKind]
    STORE_KIND_RECORDING: _ClassVar[StoreKind]
    STORE_KIND_BLUEPRINT: _ClassVar[StoreKind]

class Compression(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    COMPRESSION_UNSPECIFIED: _ClassVar[Compression]
    COMPRESSION_NONE: _ClassVar[Compression]
    COMPRESSION_LZ4: _ClassVar[Compression]

class EncoderVersion(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ENCODER_VERSION_UNSPECIFIED: _ClassVar[EncoderVersion]
    ENCODER_VERSION_V0: _ClassVar[EncoderVersion]

class DatasetKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DATASET_KIND_UNSPECIFIED: _ClassVar[DatasetKind]
    DATASET_KIND_RECORDING: _ClassVar[DatasetKind]
    DATASET_KIND_BLUEPRINT: _ClassVar[DatasetKind]
    DATASET_KIND_ASSET: _ClassVar[DatasetKind]

class IfMissingBehavior(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IF_MISSING_BEHAVIOR_UNSPECIFIED: _ClassVar[IfMissingBehavior]
    IF_MISSING_BEHAVIOR_SKIP: _ClassVar[IfMissingBehavior]
    IF_MISSING_BEHAVIOR_ERROR: _ClassVar[IfMissingBehavior]
STORE_KIND_UNSPECIFIED: StoreKind
STORE_KIND_RECORDING: StoreKind
STORE_KIND_BLUEPRINT: StoreKind
COMPRESSION_UNSPECIFIED: Compression
COMPRESSION_NONE: Compression
COMPRESSION_LZ4: Compression
ENCODER_VERSION_UNSPECIFIED: EncoderVersion
ENCODER_VERSION_V0: EncoderVersion
DATASET_KIND_UNSPECIFIED: DatasetKind
DATASET_KIND_RECORDING: DatasetKind
DATASET_KIND_BLUEPRINT: DatasetKind
DATASET_KIND_ASSET: DatasetKind
IF_MISSING_BEHAVIOR_UNSPECIFIED: IfMissingBehavior
IF_MISSING_BEHAVIOR_SKIP: IfMissingBehavior
IF_MISSING_BEHAVIOR_ERROR: IfMissingBehavior

class ApplicationId(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: str
    def __init__(self, id: _Optional[str] = ...) -> None: ...

class StoreId(_message.Message):
    __slots__ = ("kind", "recording_id", "application_id")
    KIND_FIELD_NUMBER: _ClassVar[int]
    RECORDING_ID_FIELD_NUMBER: _ClassVar[int]
    APPLICATION_ID_FIELD_NUMBER: _ClassVar[int]
    kind: StoreKind
    recording_id: str
    application_id: ApplicationId
    def __init__(self, kind: _Optional[_Union[StoreKind, str]] = ..., recording_id: _Optional[str] = ..., application_id: _Optional[_Union[ApplicationId, _Mapping]] = ...) -> None: ...

class Tuid(_message.Message):
    __slots__ = ("time_ns", "inc")
    TIME_NS_FIELD_NUMBER: _ClassVar[int]
    INC_FIELD_NUMBER: _ClassVar[int]
    time_ns: int
    inc: int
    def __init__(self, time_ns: _Optional[int] = ..., inc: _Optional[int] = ...) -> None: ...

class Schema(_message.Message):
    __slots__ = ("arrow_schema",)
    ARROW_SCHEMA_FIELD_NUMBER: _ClassVar[int]
    arrow_schema: bytes
    def __init__(self, arrow_schema: _Optional[bytes] = ...) -> None: ...

class DataframePart(_message.Message):
    __slots__ = ("encoder_version", "payload", "compression", "uncompressed_size")
    ENCODER_VERSION_FIELD_NUMBER: _ClassVar[int]
    PAYLOAD_FIELD_NUMBER: _ClassVar[int]
    COMPRESSION_FIELD_NUMBER: _ClassVar[int]
    UNCOMPRESSED_SIZE_FIELD_NUMBER: _ClassVar[int]
    encoder_version: EncoderVersion
    payload: bytes
    compression: Compression
    uncompressed_size: int
    def __init__(self, encoder_version: _Optional[_Union[EncoderVersion, str]] = ..., payload: _Optional[bytes] = ..., compression: _Optional[_Union[Compression, str]] = ..., uncompressed_size: _Optional[int] = ...) -> None: ...

class EntryId(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: Tuid
    def __init__(self, id: _Optional[_Union[Tuid, _Mapping]] = ...) -> None: ...

class SegmentId(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: str
    def __init__(self, id: _Optional[str] = ...) -> None: ...

class EntityPath(_message.Message):
    __slots__ = ("path",)
    PATH_FIELD_NUMBER: _ClassVar[int]
    path: str
    def __init__(self, path: _Optional[str] = ...) -> None: ...

class Timeline(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class TimeRange(_message.Message):
    __slots__ = ("start", "end")
    START_FIELD_NUMBER: _ClassVar[int]
    END_FIELD_NUMBER: _ClassVar[int]
    start: int
    end: int
    def __init__(self, start: _Optional[int] = ..., end: _Optional[int] = ...) -> None: ...

class IndexColumnSelector(_message.Message):
    __slots__ = ("timeline",)
    TIMELINE_FIELD_NUMBER: _ClassVar[int]
    timeline: Timeline
    def __init__(self, timeline: _Optional[_Union[Timeline, _Mapping]] = ...) -> None: ...

class DatasetHandle(_message.Message):
    __slots__ = ("entry_id", "store_kind", "dataset_kind", "dataset_url")
    ENTRY_ID_FIELD_NUMBER: _ClassVar[int]
    STORE_KIND_FIELD_NUMBER: _ClassVar[int]
    DATASET_KIND_FIELD_NUMBER: _ClassVar[int]
    DATASET_URL_FIELD_NUMBER: _ClassVar[int]
    entry_id: EntryId
    store_kind: StoreKind
    dataset_kind: DatasetKind
    dataset_url: str
    def __init__(self, entry_id: _Optional[_Union[EntryId, _Mapping]] = ..., store_kind: _Optional[_Union[StoreKind, str]] = ..., dataset_kind: _Optional[_Union[DatasetKind, str]] = ..., dataset_url: _Optional[str] = ...) -> None: ...

class ScanParametersOrderClause(_message.Message):
    __slots__ = ("descending", "nulls_last", "column_name")
    DESCENDING_FIELD_NUMBER: _ClassVar[int]
    NULLS_LAST_FIELD_NUMBER: _ClassVar[int]
    COLUMN_NAME_FIELD_NUMBER: _ClassVar[int]
    descending: bool
    nulls_last: bool
    column_name: str
    def __init__(self, descending: _Optional[bool] = ..., nulls_last: _Optional[bool] = ..., column_name: _Optional[str] = ...) -> None: ...

class ScanParameters(_message.Message):
    __slots__ = ("columns", "on_missing_columns", "filter", "limit_offset", "limit_len", "order_by", "explain_plan", "explain_filter")
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    ON_MISSING_COLUMNS_FIELD_NUMBER: _ClassVar[int]
    FILTER_FIELD_NUMBER: _ClassVar[int]
    LIMIT_OFFSET_FIELD_NUMBER: _ClassVar[int]
    LIMIT_LEN_FIELD_NUMBER: _ClassVar[int]
    ORDER_BY_FIELD_NUMBER: _ClassVar[int]
    EXPLAIN_PLAN_FIELD_NUMBER: _ClassVar[int]
    EXPLAIN_FILTER_FIELD_NUMBER: _ClassVar[int]
    columns: _containers.RepeatedScalarFieldContainer[str]
    on_missing_columns: IfMissingBehavior
    filter: str
    limit_offset: int
    limit_len: int
    order_by: _containers.RepeatedCompositeFieldContainer[ScanParametersOrderClause]
    explain_plan: bool
    explain_filter: bool
    def __init__(self, columns: _Optional[_Iterable[str]] = ..., on_missing_columns: _Optional[_Union[IfMissingBehavior, str]] = ..., filter: _Optional[str] = ..., limit_offset: _Optional[int] = ..., limit_len: _Optional[int] = ..., order_by: _Optional[_Iterable[_Union[ScanParametersOrderClause, _Mapping]]] = ..., explain_plan: _Optional[bool] = ..., explain_filter: _Optional[bool] = ...) -> None: ...

class DevAlpha(_message.Message):
    __slots__ = ("alpha", "commit")
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    COMMIT_FIELD_NUMBER: _ClassVar[int]
    alpha: int
    commit: str
    def __init__(self, alpha: _Optional[int] = ..., commit: _Optional[str] = ...) -> None: ...

class SemanticVersion(_message.Message):
    __slots__ = ("major", "minor", "patch", "rc", "alpha", "dev_alpha")
    MAJOR_FIELD_NUMBER: _ClassVar[int]
    MINOR_FIELD_NUMBER: _ClassVar[int]
    PATCH_FIELD_NUMBER: _ClassVar[int]
    RC_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    DEV_ALPHA_FIELD_NUMBER: _ClassVar[int]
    major: int
    minor: int
    patch: int
    rc: int
    alpha: int
    dev_alpha: DevAlpha
    def __init__(self, major: _Optional[int] = ..., minor: _Optional[int] = ..., patch: _Optional[int] = ..., rc: _Optional[int] = ..., alpha: _Optional[int] = ..., dev_alpha: _Optional[_Union[DevAlpha, _Mapping]] = ...) -> None: ...

class BuildInfo(_message.Message):
    __slots__ = ("crate_name", "features", "version", "rustc_version", "llvm_version", "git_hash", "git_branch", "target_triple", "build_time", "is_debug_build")
    CRATE_NAME_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    RUSTC_VERSION_FIELD_NUMBER: _ClassVar[int]
    LLVM_VERSION_FIELD_NUMBER: _ClassVar[int]
    GIT_HASH_FIELD_NUMBER: _ClassVar[int]
    GIT_BRANCH_FIELD_NUMBER: _ClassVar[int]
    TARGET_TRIPLE_FIELD_NUMBER: _ClassVar[int]
    BUILD_TIME_FIELD_NUMBER: _ClassVar[int]
    IS_DEBUG_BUILD_FIELD_NUMBER: _ClassVar[int]
    crate_name: str
    features: str
    version: SemanticVersion
    rustc_version: str
    llvm_version: str
    git_hash: str
    git_branch: str
    target_triple: str
    build_time: str
    is_debug_build: bool
    def __init__(self, crate_name: _Optional[str] = ..., features: _Optional[str] = ..., version: _Optional[_Union[SemanticVersion, _Mapping]] = ..., rustc_version: _Optional[str] = ..., llvm_version: _Optional[str] = ..., git_hash: _Optional[str] = ..., git_branch: _Optional[str] = ..., target_triple: _Optional[str] = ..., build_time: _Optional[str] = ..., is_debug_build: _Optional[bool] = ...) -> None: ...
