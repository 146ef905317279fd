"""Which token a CLI command sends, and what it says when the service refuses it."""

from __future__ import annotations

from pathlib import Path

import jwt
import pytest

from core.errors import InvalidArgumentError
from sdk_client.rest import FleetClient
from services.auth import ADMIN_TOKEN_FILE
from services.cli.client import TokenSource, resolve_token, unauthenticated_message

LOCAL = "http://127.0.0.1:8080"


def depot_token(*hosts: str) -> str:
    """A token shaped like the depot's (only its allowed_hosts claim matters to the CLI)."""
    return jwt.encode({"sub": "admin@depot", "allowed_hosts": list(hosts)}, "k" * 32, "HS256")


def data_dir_with(tmp_path: Path, content: str) -> Path:
    data = tmp_path / "data"
    data.mkdir()
    (data / ADMIN_TOKEN_FILE).write_text(content)
    return data


def test_fleet_token_comes_first(tmp_path: Path):
    data = data_dir_with(tmp_path, depot_token("localhost") + "\n")
    source = resolve_token(LOCAL, {"FLEET_TOKEN": " given-token\n", "FLEET_DATA_DIR": str(data)})
    assert source == TokenSource("given-token", "FLEET_TOKEN")


def test_then_the_admin_token_of_the_data_dir(tmp_path: Path):
    token = depot_token("localhost")
    data = data_dir_with(tmp_path, token + "\n")
    for env in ({"FLEET_DATA_DIR": str(data)}, {"FLEET_TOKEN": "  ", "FLEET_DATA_DIR": str(data)}):
        assert resolve_token(LOCAL, env) == TokenSource(token, str(data / ADMIN_TOKEN_FILE))


def test_the_data_dir_defaults_to_fleet_data_here(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    token = depot_token()
    (tmp_path / "fleet-data").mkdir()
    (tmp_path / "fleet-data" / ADMIN_TOKEN_FILE).write_text(token)
    monkeypatch.chdir(tmp_path)
    assert resolve_token("http://localhost:8080", {}).token == token
    monkeypatch.chdir(tmp_path / "fleet-data")  # no fleet-data below: no token
    assert resolve_token("http://localhost:8080", {}) == TokenSource(None, "")


def test_else_no_token(tmp_path: Path):
    assert resolve_token(LOCAL, {"FLEET_DATA_DIR": str(tmp_path / "nothing")}) == TokenSource(None, "")


@pytest.mark.parametrize("url", ["http://127.0.0.1:8080", "http://localhost:8080", "http://[::1]:8080/"])
def test_the_admin_token_goes_to_loopback_addresses(tmp_path: Path, url: str):
    token = depot_token()  # names no host at all
    assert resolve_token(url, {"FLEET_DATA_DIR": str(data_dir_with(tmp_path, token))}).token == token


def test_the_admin_token_goes_to_another_host_only_if_it_names_it(tmp_path: Path):
    token = depot_token("localhost", "fleet.example.com")
    env = {"FLEET_DATA_DIR": str(data_dir_with(tmp_path, token))}
    assert resolve_token("https://fleet.example.com", env).token == token
    elsewhere = resolve_token("http://elsewhere.example.com:8080", env)
    assert elsewhere.token is None and "not sent to elsewhere.example.com" in elsewhere.note
    # FLEET_TOKEN is sent wherever it is told to go: whoever set it chose the host
    assert resolve_token("http://elsewhere.example.com", {**env, "FLEET_TOKEN": "t"}).token == "t"


def test_a_token_file_that_cannot_be_used_is_explained(tmp_path: Path):
    empty = data_dir_with(tmp_path, "\n")
    assert resolve_token(LOCAL, {"FLEET_DATA_DIR": str(empty)}).note.endswith("is empty")
    unreadable = tmp_path / "unreadable"
    (unreadable / ADMIN_TOKEN_FILE).mkdir(parents=True)  # reading it fails, as for another user's 0600 file
    source = resolve_token(LOCAL, {"FLEET_DATA_DIR": str(unreadable)})
    assert source.token is None and "could not be read" in source.note


@pytest.mark.parametrize(
    "source",
    [
        TokenSource("t", "FLEET_TOKEN"),
        TokenSource("t", "/srv/fleet-data/admin.token"),
        TokenSource(None, ""),
        TokenSource(None, "", "/srv/fleet-data/admin.token is empty"),
    ],
)
def test_a_refusal_is_one_line_naming_fleet_token_and_tokens_create(source: TokenSource):
    message = unauthenticated_message("token abc was revoked at 2026-01-01T00:00:00Z", source)
    assert "FLEET_TOKEN" in message and "fleet tokens create" in message and "\n" not in message
    if source.origin:
        assert "was revoked" in message and source.origin in message
    assert source.note in message


def test_a_malformed_token_is_refused_without_showing_it():
    secret = "eyJhbGciOi.secret part\nsecond-line"
    with pytest.raises(InvalidArgumentError) as caught:
        FleetClient(LOCAL, token=secret)
    assert "secret part" not in str(caught.value) and "second-line" not in str(caught.value)
