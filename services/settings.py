"""The depot's settings (`Settings`, for `fleet serve`) and the base it shares with the robot
agent's (`services/agent/settings.py`): each program's read once at start (environment `FLEET_*`,
then an optional TOML file named by `FLEET_CONFIG`, then defaults) and passed down to everything
that needs it."""

from __future__ import annotations

import enum
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

from limits import parse as parse_rate_limit
from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from services.policies import Policies, Policy, PolicyOverride
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE
from services.rrd.limits import DEFAULT_DECOMPRESS_BUDGET_BYTES, DEFAULT_MAX_CHUNK_BYTES
from services.storage.objectstore import PART_BYTES, PRESIGNED_TTL_MAX_S, UPLOAD_CONCURRENCY


class Durability(enum.StrEnum):
    """When the hot tier fsyncs: after every write, every FLEET_GROUP_COMMIT_MS, or never."""

    ALWAYS = "always"
    INTERVAL = "interval"
    OFF = "off"


class DirectReads(enum.StrEnum):
    """How catalog clients read sealed runs' chunks: through the depot (FetchChunks), or from the
    warm bucket by presigned ranged GETs the catalog server hands out."""

    OFF = "off"
    PRESIGNED = "presigned"


class AuthMode(enum.StrEnum):
    """on: every request and stream needs a token; off: none is checked (a loopback bind only)."""

    ON = "on"
    OFF = "off"


# Property fields never written to disk nor served (FLEET_SECRET_FIELDS): a field is secret when
# one of these, as words, appears in its name (see SecretFields).
DEFAULT_SECRET_FIELDS = (
    "token",
    "password",
    "passwd",
    "secret",
    "api_key",
    "apikey",
    "access_key",
    "secret_key",
    "private_key",
    "credential",
    "credentials",
    "authorization",
    "auth_token",
)


# The agent's own settings are named `agent_*` (FLEET_AGENT_*): a TOML file shared by both programs
# on one machine holds them beside the depot's, and `fleet serve` leaves them to `fleet agent`.
AGENT_PREFIX = "agent_"


def name_list(value: Any) -> Any:
    """`["token", "password"]` (JSON, TOML) or `token,password`: how a list setting is written."""
    if isinstance(value, str):
        text = value.strip()
        return json.loads(text) if text.startswith("[") else [n.strip() for n in text.split(",") if n.strip()]
    return value


class SharedSettings(BaseSettings):
    """What `fleet serve` and `fleet agent` both read, under the same names: the robot's spool is
    the depot's hot tier and ingest run on the robot, so the ingest settings apply to both. Each
    program's class adds its own fields; neither knows the other's."""

    model_config = SettingsConfigDict(env_prefix="FLEET_", extra="forbid")

    max_message_size: int = Field(
        DEFAULT_MAX_MESSAGE_SIZE, gt=0, description="largest RRD/gRPC message accepted, in bytes"
    )
    secret_fields: Annotated[list[str], NoDecode] = Field(
        default_factory=lambda: list(DEFAULT_SECRET_FIELDS),
        description="recording property fields never stored nor served: a field is secret if one of these "
        "names, as words, appears in its name (token matches ingest_token, apiKey matches api_key; a JSON list "
        "or comma-separated)",
    )
    group_commit_ms: int = Field(
        200, gt=0, description="with durability=interval (the agent's: agent_durability), fsync every this many ms"
    )
    close_after_s: float = Field(60.0, gt=0, description="a live run with no data for this long is closed")
    default_robot: str = Field(
        "unknown-robot", pattern=r"^[A-Za-z0-9._-]{1,128}$", description="robot id of runs that name none"
    )

    @field_validator("secret_fields", mode="before")
    @classmethod
    def _secret_field_names(cls, value: Any) -> Any:
        return name_list(value)

    @classmethod
    def other_programs_key(cls, key: str) -> bool:
        """Whether `key` of the TOML file is a setting of the other program (left to it, not
        refused as unknown)."""
        return False

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # The environment needs no such care: only the variables of this class's fields are read,
        # so the other program's FLEET_* variables (and any unknown one) are never looked at.
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        config = os.environ.get("FLEET_CONFIG")
        if config:
            sources.append(ConfigFile(settings_cls, Path(config), cls.other_programs_key))
        return tuple(sources)


class ConfigFile(TomlConfigSettingsSource):
    """The TOML file named by FLEET_CONFIG, less the other program's keys: one file may serve both
    programs on one machine, while a key neither reads (a typo) is still refused."""

    def __init__(self, settings_cls: type[BaseSettings], path: Path, others: Callable[[str], bool]) -> None:
        super().__init__(settings_cls, toml_file=path)
        self.others = others

    def __call__(self) -> dict[str, Any]:
        return {key: value for key, value in super().__call__().items() if not self.others(key)}


class Settings(SharedSettings):
    """`fleet serve`'s settings (the depot's)."""

    data_dir: Path = Field(
        Path("./fleet-data"), description="hot tier and embedded defaults live here; one fleet serve per data dir"
    )
    http_addr: str = Field("0.0.0.0:8080", description="REST API address")
    grpc_addr: str = Field(
        "0.0.0.0:51234", description="Rerun message proxy address (Rerun's server port; 9876 is the viewer's)"
    )
    catalog_url: str = Field(
        "", description="duckdb:///PATH or postgresql+psycopg://... (default: DuckDB file in the data dir)"
    )
    catalog_timeout_s: float = Field(
        10.0, gt=0, description="Postgres catalog: statement timeout and pool wait of every call (connect: 5 s at most)"
    )
    warm_url: str = Field("", description="file:///PATH or s3://bucket/prefix (default: data dir/warm)")
    cold_url: str = Field("", description="file:///PATH or s3://bucket/prefix (default: data dir/cold)")
    s3_endpoint_url: str | None = Field(None, description="S3-compatible endpoint; credentials from AWS_*")
    s3_region: str | None = Field(None, description="S3 region (default: from AWS_* settings)")
    s3_part_bytes: int = Field(
        PART_BYTES,
        ge=5 * 1024 * 1024,
        le=5 * 1024**3,
        description="parts of a multipart upload to S3 (objects larger than this are sent in parts), in bytes; "
        "S3 takes 5 MiB to 5 GiB",
    )
    s3_upload_concurrency: int = Field(
        UPLOAD_CONCURRENCY,
        ge=1,
        le=64,
        description="parts of one upload sent at once; an upload holds up to this many parts in memory",
    )
    s3_loop_reads: bool = Field(
        True,
        description="whole downloads of sealed runs read the S3 object on the event loop (one GET signed for the "
        "read); false: through botocore in a thread. Off by itself where HTTPS_PROXY/HTTP_PROXY applies to the "
        "endpoint",
    )
    direct_reads: DirectReads = Field(
        DirectReads.OFF,
        description="off | presigned: catalog clients (Rerun's SDK) read sealed runs' chunks straight from the "
        "s3:// warm bucket by presigned ranged GETs, not through the depot (docs/catalog-server.md)",
    )
    direct_url_ttl_s: int = Field(
        600, ge=60, le=PRESIGNED_TTL_MAX_S, description="presigned chunk URLs last this long (at most 15 minutes)"
    )
    direct_reads_endpoint_url: str | None = Field(
        None,
        description="the S3 endpoint presigned URLs name, when clients reach the bucket by another address than "
        "the depot (default: s3_endpoint_url)",
    )
    cold_storage_class: str = Field(
        "",
        description="archive by moving warm objects to this S3 storage class "
        "(GLACIER, DEEP_ARCHIVE, STANDARD_IA, ...) instead of copying to cold_url",
    )
    max_chunk_bytes: int = Field(
        DEFAULT_MAX_CHUNK_BYTES,
        gt=0,
        description="largest chunk accepted once decompressed, in bytes (checked "
        "before decompressing: LZ4 may declare 255x its size)",
    )
    decompress_budget_bytes: int = Field(
        DEFAULT_DECOMPRESS_BUDGET_BYTES,
        gt=0,
        description="decompressed chunk bytes held at once by all readers of stored runs (downloads, sealing) together",
    )
    durability: Durability = Field(
        Durability.INTERVAL, description="hot-tier fsync: always (before answering) | interval (group commit) | off"
    )
    min_free_bytes: int = Field(1 << 30, ge=0, description="refuse new data when the hot disk has less free")
    reserve_bytes: int = Field(
        64 << 20,
        ge=0,
        description="held in reserve on the data disk for the catalog "
        "(released when the disk is full); promotion never takes the disk below it",
    )
    max_streams: int = Field(1000, gt=0, description="most concurrent gRPC streams on this node")
    replay_bytes: int = Field(
        64 * 1024 * 1024, ge=0, description="recent live data kept for ReadMessages readers (0: none)"
    )
    catalog_flush_s: float = Field(2.0, gt=0, description="how often live runs' figures are written to the catalog")
    promote_after_s: float = Field(600.0, ge=0, description="a closed run idle this long is sealed into the warm tier")
    promote_below_free_bytes: int = Field(
        4 << 30,
        ge=0,
        description="hot high-water mark: with less free disk, "
        "closed runs are promoted oldest first ahead of promote_after_s",
    )
    warm_days: float = Field(30.0, ge=0, description="default policy: days warm before archiving to cold")
    cold_days: float = Field(365.0, ge=0, description="default policy: days cold before deletion (0: none)")
    restore_days: float = Field(7.0, gt=0, description="a restored cold run serves for this many days")
    retention_policies: list[PolicyOverride] = Field(
        default_factory=list,
        description="overrides by robot or application: a JSON list or TOML "
        "[[retention_policies]] tables of name, robot|application, warm_days, cold_days",
    )
    promote_interval_s: float = Field(30.0, gt=0, description="how often the promotion job runs")
    retention_interval_s: float = Field(600.0, gt=0, description="how often archive, restore and expiry jobs run")
    scheduler: bool = Field(True, description="run the retention jobs inside fleet serve")
    lakehouse: bool = Field(
        True,
        description="keep the analytics tables as Iceberg tables under the warm store's lakehouse/ prefix, "
        "cataloged in the catalog database, for outside engines (docs/lakehouse.md)",
    )
    lakehouse_sync_s: float = Field(30.0, gt=0, description="how often sealed runs' rows are copied to the lakehouse")
    lakehouse_maintenance_s: float = Field(
        3600.0, gt=0, description="how often the lakehouse's small files are compacted and old snapshots expired"
    )
    lakehouse_keep_s: float = Field(
        86_400.0,
        ge=600,
        description="how long the lakehouse keeps a snapshot (time travel; a deleted run's rows stay in "
        "older snapshots' files until they expire)",
    )
    sql_max_rows: int = Field(100_000, gt=0, description="most rows a SQL answer may have")
    sql_timeout_s: float = Field(
        30.0, gt=0, description="a SQL query taking longer from its arrival (queue included) is stopped"
    )
    sql_memory_limit: str = Field(
        "2GB",
        pattern=r"(?i)^\s*\d+(\.\d+)?\s*([kmgt]i?b|b)?\s*$",
        description="memory a SQL query's worker process may use (e.g. 2GB, 512MiB)",
    )
    sql_threads: int = Field(4, gt=0, description="threads a SQL query may use")
    sql_workers: int = Field(2, gt=0, description="SQL queries running at once, each in a worker process")
    sql_queue: int = Field(8, ge=0, description="SQL queries waiting for a worker; more are refused (429)")
    sql_read_ahead_files: int = Field(
        1000,
        ge=0,
        description="lakehouse data files whose footers an idle SQL worker reads ahead for the next query "
        "(those of the tables the last query read); 0 reads none ahead",
    )
    auth: AuthMode = Field(
        AuthMode.ON, description="on: every request and stream needs a token; off: nothing is checked (loopback only)"
    )
    insecure: bool = Field(
        False, description="allow auth=off on a non-loopback bind: anyone who reaches the ports can do anything"
    )
    auth_key: SecretStr | None = Field(
        None,
        description="key signing tokens and links, at least 32 characters; the same on every node "
        "(default: generated at first start into DATA_DIR/auth.key, mode 0600)",
    )
    auth_previous_keys: Annotated[list[SecretStr], NoDecode] = Field(
        default_factory=list,
        description="earlier signing keys still accepted while their tokens are replaced (key rotation; "
        "a JSON list or comma-separated)",
    )
    public_hosts: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="host names clients reach the depot by, written into tokens' allowed_hosts: Rerun's viewer "
        "and SDK send a token only to these (default: localhost, 127.0.0.1 and this machine's names)",
    )
    public_url: str = Field(
        "",
        description="base URL of the REST API in signed links (default: the address the request came to if its "
        "host is one of public_hosts, else the bind address)",
    )
    link_ttl_s: float = Field(
        24 * 3600.0, gt=0, le=7 * 24 * 3600.0, description="signed download links last this long unless asked"
    )
    auth_wait_s: float = Field(
        10.0, gt=0, description="an SDK stream without a token in its metadata has this long to send its fleet token"
    )
    auth_buffer_bytes: int = Field(
        16 << 20, gt=0, description="what such a stream may send before its token, held in memory and then kept"
    )
    auth_buffer_total_bytes: int = Field(
        64 << 20,
        gt=0,
        description="what all streams still waiting for their token may hold together, per process (beyond it a "
        "stream is refused, RESOURCE_EXHAUSTED): the bound on that memory whatever FLEET_MAX_STREAMS is",
    )
    auth_cache_s: float = Field(
        5.0, ge=0, description="a token's revocation is seen by every node within this many seconds"
    )
    auth_catalog_wait_s: float = Field(
        2.0,
        gt=0,
        le=60.0,
        description="the longest a token check waits for the catalog before it answers from what it knows (else 503)",
    )
    auth_stale_s: float = Field(
        600.0,
        ge=0,
        description="while the catalog does not answer, a token it confirmed within this many seconds is "
        "still accepted (a revocation made meanwhile takes effect within it); others are refused 503",
    )
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="web origins (https://console.example.com) allowed to call the API with a token; any "
        "origin may still fetch recordings by signed link",
    )
    sql_rate: str = Field("60/minute", description="SQL queries per token (limits notation: 60/minute, 5/second)")
    download_rate: str = Field("120/minute", description="recording downloads per token or signed link")

    # many depot processes on one Postgres catalog and one bucket (docs/scale-out.md)
    workers: int = Field(
        0,
        ge=0,
        description="processes serving the two ports of this host (0: one per core with a Postgres catalog; "
        "the embedded DuckDB catalog has a single writer, so one)",
    )
    node_id: str = Field(
        "",
        pattern=r"^[A-Za-z0-9._-]{0,200}$",
        description="this node's name in the catalog, unique among the depot's processes (default: the host "
        "name and the REST port, HOST-8080; workers are NAME-w0, NAME-w1, ...)",
    )
    peer_addr: str = Field(
        "127.0.0.1:0",
        description="where other depot processes hand this node chunks of the runs it owns (gRPC); on several "
        "hosts an address they reach, such as 0.0.0.0:51235 (workers take PORT+i; 0: any free port)",
    )
    peer_advertise: str = Field(
        "",
        description="the host other nodes reach the peer port by (default: its bind host, or this host's name "
        "when that is 0.0.0.0)",
    )
    lease_s: float = Field(
        10.0, gt=0, description="a node that stops heart-beating this long loses its hot runs to the other nodes"
    )

    # the corpus: what rules make of runs (docs/corpus.md)
    max_events_per_run: int = Field(
        10_000, gt=0, description="a rule stops adding events to a run at this many, and the run's answer says so"
    )
    rules_backfill_bytes_s: int = Field(
        32 << 20,
        gt=0,
        description="bytes per second the rules backfill reads from stored runs (re-evaluating them after a rules "
        "change), so that serving is not starved",
    )
    rules_backfill_interval_s: float = Field(
        300.0, gt=0, description="how often the rules backfill job looks for runs the running rules have not evaluated"
    )
    # webhooks (docs/corpus.md)
    webhook_hosts: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="hosts webhooks may be sent to, as HOST (any port) or HOST:PORT (a JSON list or "
        "comma-separated; none: no webhook can be added). This depot's own ports on loopback and link-local "
        "or cloud metadata addresses are refused unless their very HOST:PORT is listed",
    )
    silent_after_s: float = Field(
        300.0, gt=0, description="a robot whose live run sends nothing this long is told of (robot.silent)"
    )
    webhook_interval_s: float = Field(5.0, gt=0, description="how often due webhook deliveries are sent")
    webhook_timeout_s: float = Field(5.0, gt=0, description="a webhook endpoint has this long to answer")
    webhook_batch: int = Field(50, gt=0, description="most webhook deliveries attempted per pass")
    webhook_workers: int = Field(4, gt=0, description="webhook deliveries sent at once")
    webhook_retry_s: float = Field(
        24 * 3600.0, gt=0, description="a webhook delivery is retried with backoff this long, then given up"
    )

    # dataset exports (docs/datasets.md)
    export_urls: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="where the depot may write dataset exports: file:///PATH or s3://BUCKET/PREFIX URLs (a JSON "
        "list or comma-separated); an export's target must be one of them or under one. None: the depot writes no "
        "export (the command line still exports to a local folder)",
    )
    export_interval_s: float = Field(2.0, gt=0, description="how often the depot looks for a queued dataset export")

    # imports: MCAP uploads converted by the Rerun CLI (docs/mcap.md)
    rerun_cli: str | None = Field(
        None, description="the `rerun` executable that converts MCAP uploads (default: the installed rerun-sdk's)"
    )
    mcap_timeout_s: float = Field(3600.0, gt=0, description="a conversion of one MCAP file may take this long")
    mcap_memory_mb: int = Field(
        4096, ge=64, description="memory (MiB, resident and not file-backed) a conversion may use; past it, it fails"
    )
    mcap_max_output_ratio: float = Field(
        20.0, gt=0, description="a converted recording may be this many times its MCAP file's size (at least 256 MiB)"
    )
    import_quarantine_days: float = Field(
        14.0, gt=0, description="a failed MCAP upload's original is kept this long for an admin and for a retry"
    )

    @property
    def hot_dir(self) -> Path:
        return self.data_dir / "hot"

    @property
    def policies(self) -> Policies:
        return Policies(Policy("default", self.warm_days, self.cold_days), tuple(self.retention_policies))

    @field_validator("sql_rate", "download_rate")
    @classmethod
    def _rate(cls, value: str) -> str:
        try:
            parse_rate_limit(value)
        except ValueError as exc:
            raise ValueError(f"{value!r} is not a rate such as 60/minute or 5/second") from exc
        return value

    @field_validator("public_hosts", "cors_origins", "auth_previous_keys", "export_urls", mode="before")
    @classmethod
    def _name_list(cls, value: Any) -> Any:
        return name_list(value)

    @classmethod
    def other_programs_key(cls, key: str) -> bool:
        return key.startswith(AGENT_PREFIX)

    @field_validator("webhook_hosts", mode="before")
    @classmethod
    def _webhook_hosts(cls, value: Any) -> Any:
        return [h.strip().lower() for h in name_list(value)] if value is not None else value

    @field_validator("auth_key")
    @classmethod
    def _long_key(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and len(value.get_secret_value()) < 32:
            raise ValueError(
                "auth_key must be at least 32 characters (python -c 'import secrets; print(secrets.token_urlsafe(32))')"
            )
        return value

    @model_validator(mode="after")
    def _budget_holds_a_chunk(self) -> Settings:
        if self.decompress_budget_bytes < self.max_chunk_bytes:
            raise ValueError(
                f"decompress_budget_bytes ({self.decompress_budget_bytes}) must be at least "
                f"max_chunk_bytes ({self.max_chunk_bytes}): the largest chunk must fit in it"
            )
        return self

    @model_validator(mode="after")
    def _embedded_defaults(self) -> Settings:
        data = self.data_dir.resolve()
        if not self.catalog_url:
            self.catalog_url = f"duckdb:///{data / 'catalog.duckdb'}"
        if not self.warm_url:
            self.warm_url = (data / "warm").as_uri()
        if not self.cold_url:
            self.cold_url = (data / "cold").as_uri()
        return self

    @model_validator(mode="after")
    def _direct_reads_need_s3(self) -> Settings:
        # after _embedded_defaults: the default warm store is a folder
        if self.direct_reads == DirectReads.PRESIGNED and not self.warm_url.startswith("s3://"):
            raise ValueError(
                f"direct_reads=presigned needs an s3:// warm_url ({self.warm_url} cannot presign URLs): "
                "set FLEET_WARM_URL=s3://BUCKET/PREFIX or FLEET_DIRECT_READS=off"
            )
        return self


def load_settings(**overrides: Any) -> Settings:
    """Read the settings once; `overrides` (e.g. command-line flags) win over everything."""
    return Settings(**{k: v for k, v in overrides.items() if v is not None})
