"""The one settings object: read once at start (environment `FLEET_*`, then an optional TOML
file named by `FLEET_CONFIG`, then defaults) and passed down to everything that needs it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from pydantic import Field, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="FLEET_", extra="forbid")

    data_dir: Path = Field(Path("./fleet-data"), description="hot tier and embedded defaults live here")
    http_addr: str = Field("0.0.0.0:8080", description="REST API address")
    grpc_addr: str = Field("0.0.0.0:9876", description="Rerun message proxy address")
    catalog_url: str = Field("", description="duckdb:///PATH or postgresql+psycopg://... "
                             "(default: DuckDB file in the data dir)")
    warm_url: str = Field("", description="file:///PATH or s3://bucket/prefix (default: data dir/warm)")
    cold_url: str = Field("", description="file:///PATH or s3://bucket/prefix (default: data dir/cold)")
    s3_endpoint_url: str | None = Field(None, description="S3-compatible endpoint; credentials from AWS_*")
    api_url: str = Field("http://127.0.0.1:8080", description="where CLI commands reach the service")
    max_message_size: int = Field(DEFAULT_MAX_MESSAGE_SIZE, gt=0,
                                  description="largest RRD/gRPC message accepted, in bytes")

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

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        config = os.environ.get("FLEET_CONFIG")
        if config:
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=Path(config)))
        return tuple(sources)


def load_settings(**overrides: Any) -> Settings:
    """Read the settings once; `overrides` (e.g. command-line flags) win over everything."""
    return Settings(**{k: v for k, v in overrides.items() if v is not None})
