"""Signing keys: generated once into the data dir (0600) and reused, or given by setting; earlier
keys still check what they signed (rotation)."""

from __future__ import annotations

import datetime as dt
import stat
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from core.errors import PermissionDeniedError, UnauthenticatedError
from services.auth import links
from services.auth.keys import KEY_FILE, load_signing_keys, write_private
from services.auth.tokens import Auth
from services.settings import load_settings

OLD_KEY = "old-" + "a" * 40
NEW_KEY = "new-" + "b" * 40


def test_a_generated_key_is_private_and_reused(tmp_path: Path):
    settings = load_settings(data_dir=tmp_path)
    first = load_signing_keys(settings)
    path = tmp_path / KEY_FILE
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(first.current.secret) >= 32
    assert load_signing_keys(settings).current == first.current  # a restart signs with the same key
    assert load_signing_keys(load_settings(data_dir=tmp_path / "other")).current != first.current


def test_the_key_setting_wins_over_the_file(tmp_path: Path):
    load_signing_keys(load_settings(data_dir=tmp_path))  # a file exists
    keys = load_signing_keys(load_settings(data_dir=tmp_path, auth_key=NEW_KEY))
    assert keys.current.secret == NEW_KEY.encode()
    fresh = tmp_path / "fresh"
    load_signing_keys(load_settings(data_dir=fresh, auth_key=NEW_KEY))
    assert not (fresh / KEY_FILE).exists()  # nothing generated when the key is given


def test_a_short_key_setting_is_refused():
    with pytest.raises(ValueError, match="at least 32 characters"):
        load_settings(auth_key="short")


def test_write_private_never_overwrites(tmp_path: Path):
    path = tmp_path / "secret"
    write_private(path, "one\n")
    with pytest.raises(FileExistsError):
        write_private(path, "two\n")
    assert path.read_text() == "one\n" and stat.S_IMODE(path.stat().st_mode) == 0o600


def test_previous_keys_still_check_tokens_and_links_they_signed(tmp_path: Path, catalog: sessionmaker[Session]):
    before = Auth(enabled=True, keys=load_signing_keys(load_settings(auth_key=OLD_KEY)), catalog=catalog)
    issued = before.issue(subject="alice", scopes=["read"], created_by="test")
    expires = dt.datetime.now(dt.UTC) + dt.timedelta(hours=1)
    assert before.keys is not None
    link = links.sign(before.keys, "run-1", [("include", "/world/**")], expires, issued.record.id)

    rotated = load_signing_keys(load_settings(auth_key=NEW_KEY, auth_previous_keys=f"{OLD_KEY}"))
    after = Auth(enabled=True, keys=rotated, catalog=catalog)
    assert after.authenticate(issued.token, "rest").subject == "alice"
    assert after.link_principal("run-1", link).token_id == issued.record.id
    assert after.claims(after.issue(subject="bob", scopes=["read"], created_by="test").token)["sub"] == "bob"

    dropped = Auth(enabled=True, keys=load_signing_keys(load_settings(auth_key=NEW_KEY)), catalog=catalog)
    with pytest.raises(UnauthenticatedError, match="FLEET_AUTH_PREVIOUS_KEYS"):
        dropped.authenticate(issued.token, "rest")
    with pytest.raises(PermissionDeniedError, match="signature does not match"):
        dropped.link_principal("run-1", link)
