"""At start: auth off only on loopback (unless --insecure), and the first admin token, once."""

from __future__ import annotations

import logging
import stat
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from core.errors import InvalidArgumentError
from services.auth import ADMIN_TOKEN_FILE
from services.auth.bootstrap import check_auth_bind, ensure_admin_token, open_auth
from services.auth.scopes import Scope
from services.auth.tokens import Auth
from services.settings import load_settings
from services.startup import is_loopback


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost"])
def test_loopback_hosts(host: str):
    assert is_loopback(host)


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "", "10.0.0.5", "depot.example"])
def test_hosts_others_reach(host: str):
    assert not is_loopback(host)


@pytest.mark.parametrize("public", ["0.0.0.0", "10.0.0.5", "depot.example"])
def test_auth_off_on_a_public_address_is_refused_naming_insecure(public: str):
    settings = load_settings(auth="off")
    with pytest.raises(InvalidArgumentError) as refused:
        check_auth_bind(settings, ["127.0.0.1", public])
    message = refused.value.message
    assert "--insecure" in message and public in message and "\n" not in message


def test_auth_off_on_a_public_address_with_insecure_starts_with_a_warning():
    warning = check_auth_bind(load_settings(auth="off", insecure=True), ["0.0.0.0", "127.0.0.1"])
    assert warning is not None and "auth is off" in warning and "--insecure" in warning


def test_auth_off_on_loopback_starts_and_says_so():
    warning = check_auth_bind(load_settings(auth="off"), ["127.0.0.1", "::1"])
    assert warning is not None and "auth is off" in warning and "loopback" in warning


def test_auth_on_binds_anywhere():
    assert check_auth_bind(load_settings(auth="on"), ["0.0.0.0", "::"]) is None


def test_the_admin_token_is_written_once_privately(tmp_path: Path, catalog: sessionmaker[Session]):
    auth = open_auth(load_settings(data_dir=tmp_path, auth="on"), catalog)
    issued = ensure_admin_token(auth, tmp_path)
    assert issued is not None
    path = tmp_path / ADMIN_TOKEN_FILE
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert path.read_text() == issued.token + "\n"
    principal = auth.authenticate(path.read_text().strip(), "rest")
    assert principal.scopes == {Scope.ADMIN}

    again = open_auth(load_settings(data_dir=tmp_path, auth="on"), catalog)  # a restart: same key file
    assert ensure_admin_token(again, tmp_path) is None
    assert path.read_text() == issued.token + "\n" and len(again.tokens()) == 1


def test_a_revoked_admin_token_file_is_left_alone_and_reported(
    tmp_path: Path, catalog: sessionmaker[Session], caplog: pytest.LogCaptureFixture
):
    auth = open_auth(load_settings(data_dir=tmp_path, auth="on"), catalog)
    issued = ensure_admin_token(auth, tmp_path)
    assert issued is not None
    auth.revoke(issued.record.id, "admin")
    with caplog.at_level(logging.WARNING):
        assert ensure_admin_token(auth, tmp_path) is None
    assert (tmp_path / ADMIN_TOKEN_FILE).read_text() == issued.token + "\n"
    assert "delete it and restart" in caplog.text and issued.token not in caplog.text
    assert len(auth.tokens()) == 0


def test_auth_off_makes_no_admin_token(tmp_path: Path):
    assert ensure_admin_token(Auth(enabled=False, keys=None, catalog=None), tmp_path) is None
    assert not (tmp_path / ADMIN_TOKEN_FILE).exists()
