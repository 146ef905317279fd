"""At start: auth off only on loopback (unless --insecure), and the first admin token, once."""

from __future__ import annotations

import io
import logging
import os
import stat
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from core.errors import InvalidArgumentError
from services.auth import ADMIN_TOKEN_FILE
from services.auth.bootstrap import announce_admin, check_auth_bind, ensure_admin_token, open_auth
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


def test_a_first_start_on_a_log_says_where_the_admin_token_is_never_the_token(
    tmp_path: Path, catalog: sessionmaker[Session]
):
    issued = ensure_admin_token(open_auth(load_settings(data_dir=tmp_path, auth="on"), catalog), tmp_path)
    assert issued is not None
    log = io.StringIO()  # stdout as systemd, docker or a redirect take it: not a terminal
    announce_admin(issued, tmp_path, log)
    said = log.getvalue()
    assert issued.token not in said and issued.token.rsplit(".", 1)[1] not in said
    assert str(tmp_path / ADMIN_TOKEN_FILE) in said and "first start" in said and said.count("\n") == 1
    assert (tmp_path / ADMIN_TOKEN_FILE).read_text() == issued.token + "\n"  # where it is, always


def test_a_first_start_on_a_terminal_shows_the_admin_token_once(tmp_path: Path, catalog: sessionmaker[Session]):
    issued = ensure_admin_token(open_auth(load_settings(data_dir=tmp_path, auth="on"), catalog), tmp_path)
    assert issued is not None
    main, side = os.openpty()  # a real terminal device, as an interactive `fleet serve` has
    try:
        with open(side, "w", closefd=False) as terminal:
            assert terminal.isatty()
            announce_admin(issued, tmp_path, terminal)
        shown = b""
        while issued.token.encode() not in shown and len(shown) < 10_000:
            shown += os.read(main, 4096)  # what the terminal received (blocks only until it is there)
    finally:
        os.close(side)
        os.close(main)
    text = shown.decode()
    assert text.count(issued.token) == 1 and "shown once" in text and str(tmp_path / ADMIN_TOKEN_FILE) in text


def test_nothing_is_announced_when_no_admin_token_was_made(tmp_path: Path):
    out = io.StringIO()
    announce_admin(None, tmp_path, out)
    assert out.getvalue() == ""


def test_the_catalog_wait_of_a_token_check_is_the_setting(tmp_path: Path, catalog: sessionmaker[Session]):
    settings = load_settings(data_dir=tmp_path, auth="on", auth_catalog_wait_s=7.5)
    assert open_auth(settings, catalog)._known.wait_s == 7.5
    assert open_auth(load_settings(data_dir=tmp_path, auth="on"), catalog)._known.wait_s == 2.0
