from pathlib import Path

import pytest
from pydantic import ValidationError

from services.settings import load_settings


def test_embedded_defaults_live_in_the_data_dir(tmp_path, monkeypatch):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    settings = load_settings(data_dir=tmp_path)
    assert settings.catalog_url == f"duckdb:///{tmp_path.resolve() / 'catalog.duckdb'}"
    assert settings.warm_url == (tmp_path.resolve() / "warm").as_uri()
    assert settings.cold_url == (tmp_path.resolve() / "cold").as_uri()
    assert settings.http_addr == "0.0.0.0:8080"
    assert settings.grpc_addr == "0.0.0.0:51234"


def test_environment_then_toml_then_defaults(tmp_path, monkeypatch):
    config = tmp_path / "fleet.toml"
    config.write_text('http_addr = "127.0.0.1:1111"\ngrpc_addr = "127.0.0.1:2222"\n')
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    monkeypatch.setenv("FLEET_HTTP_ADDR", "127.0.0.1:3333")
    settings = load_settings()
    assert settings.http_addr == "127.0.0.1:3333"  # environment wins over the file
    assert settings.grpc_addr == "127.0.0.1:2222"  # the file wins over defaults
    assert load_settings(http_addr="127.0.0.1:4444").http_addr == "127.0.0.1:4444"  # flags win


def test_unknown_toml_key_is_refused(tmp_path, monkeypatch):
    config = tmp_path / "fleet.toml"
    config.write_text('htp_addr = "127.0.0.1:1111"\n')
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    with pytest.raises(ValidationError, match="htp_addr"):
        load_settings()


def test_the_agents_keys_are_left_to_it(tmp_path, monkeypatch):
    """One TOML file may serve `fleet serve` and `fleet agent` on one machine: the agent's keys
    (`agent_*`, tests/services/agent/test_settings.py) are not the depot's, nor refused by it."""
    config = tmp_path / "fleet.toml"
    config.write_text('http_addr = "127.0.0.1:1111"\nagent_spool = "spool"\nagent_retain_hours = -1\n')
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    settings = load_settings()
    assert settings.http_addr == "127.0.0.1:1111" and not hasattr(settings, "agent_spool")


def test_unknown_variables_are_not_read(monkeypatch):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    monkeypatch.setenv("FLEET_HTP_ADDR", "127.0.0.1:1111")  # a variable is looked up by name, never listed
    monkeypatch.setenv("FLEET_AGENT_RETAIN_HOURS", "-1")  # the agent's, invalid for it
    assert load_settings().http_addr == "0.0.0.0:8080"


def test_max_message_size_must_be_positive(monkeypatch):
    monkeypatch.setenv("FLEET_MAX_MESSAGE_SIZE", "0")
    with pytest.raises(ValidationError, match="max_message_size"):
        load_settings(data_dir=Path("x"))


def test_secret_fields_from_json_or_comma_separated(monkeypatch):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    assert "password" in load_settings().secret_fields and "token" in load_settings().secret_fields
    monkeypatch.setenv("FLEET_SECRET_FIELDS", "token, vin")
    assert load_settings().secret_fields == ["token", "vin"]
    monkeypatch.setenv("FLEET_SECRET_FIELDS", '["pin", "serial_key"]')
    assert load_settings().secret_fields == ["pin", "serial_key"]
    assert load_settings(secret_fields="a,b").secret_fields == ["a", "b"]  # the --secret-fields flag


def test_chunk_limits(monkeypatch):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    settings = load_settings()
    assert settings.max_chunk_bytes == settings.max_message_size == 256 * 1024 * 1024
    assert settings.decompress_budget_bytes == 2 * settings.max_chunk_bytes
    monkeypatch.setenv("FLEET_MAX_CHUNK_BYTES", str(1 << 30))
    with pytest.raises(ValidationError, match="decompress_budget_bytes"):
        load_settings()  # the largest chunk must fit in the budget
    monkeypatch.setenv("FLEET_DECOMPRESS_BUDGET_BYTES", str(1 << 30))
    assert load_settings().max_chunk_bytes == 1 << 30
