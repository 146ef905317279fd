"""Signed links: an HMAC over the run, every parameter and the expiry; any change, the passing of
the expiry, or the revocation of the token that asked for it refuses the link."""

from __future__ import annotations

import datetime as dt

import pytest

from core.errors import PermissionDeniedError
from services.auth import links
from services.auth.scopes import Scope
from services.auth.tokens import FORBIDDEN, Auth
from tests.services.auth.conftest import KEYS, OTHER_KEYS

NOW = dt.datetime(2030, 1, 2, 3, 4, 5, tzinfo=dt.UTC)
RUN = "run-1"
PARAMS = [("include", "/world/**"), ("include", "/robot/speed"), ("timeline", "frame"), ("start", "3")]


def _signed(expires_in: dt.timedelta = dt.timedelta(hours=1), by: str = "token-1") -> list[tuple[str, str]]:
    return links.sign(KEYS, RUN, PARAMS, NOW + expires_in, by)


def test_a_signed_link_verifies_and_names_its_token():
    signed = _signed()
    assert [k for k, _ in signed] == ["include", "include", "timeline", "start", "expires", "by", "sig"]
    assert links.verify(KEYS, RUN, signed, NOW) == "token-1"
    assert links.verify(KEYS, RUN, list(reversed(signed)), NOW) == "token-1"  # order does not matter


def test_signing_replaces_any_signature_fields_given():
    given = [*PARAMS, ("sig", "x"), ("expires", "1"), ("by", "someone")]
    signed = links.sign(KEYS, RUN, given, NOW + dt.timedelta(hours=1), "token-1")
    assert [v for k, v in signed if k == "by"] == ["token-1"] and len([k for k, _ in signed if k == "sig"]) == 1


def _changed(signed: list[tuple[str, str]], key: str, value: str) -> list[tuple[str, str]]:
    out, done = [], False
    for k, v in signed:
        if k == key and not done:
            out.append((k, value))
            done = True
        else:
            out.append((k, v))
    return out


@pytest.mark.parametrize(
    "tamper",
    [
        pytest.param(lambda s: _changed(s, "include", "/**"), id="param changed"),
        pytest.param(lambda s: _changed(s, "start", "0"), id="start changed"),
        pytest.param(lambda s: [*s, ("exclude", "/secret/**")], id="param added"),
        pytest.param(lambda s: [*s, ("include", "/world/**")], id="param repeated"),
        pytest.param(lambda s: [p for p in s if p != ("include", "/robot/speed")], id="param removed"),
        pytest.param(lambda s: _changed(s, "expires", str(int(NOW.timestamp()) + 10**8)), id="expiry pushed"),
        pytest.param(lambda s: _changed(s, "by", "token-2"), id="signer changed"),
        pytest.param(lambda s: _changed(s, "sig", "0" * 64), id="signature changed"),
    ],
)
def test_any_change_breaks_the_signature(tamper):
    with pytest.raises(PermissionDeniedError, match="signature does not match") as refused:
        links.verify(KEYS, RUN, tamper(_signed()), NOW)
    assert refused.value.http_status() == 403


def test_the_signature_covers_the_run():
    with pytest.raises(PermissionDeniedError, match="signature does not match"):
        links.verify(KEYS, "run-2", _signed(), NOW)


def test_another_depots_key_does_not_verify():
    with pytest.raises(PermissionDeniedError, match="signature does not match"):
        links.verify(OTHER_KEYS, RUN, _signed(), NOW)


@pytest.mark.parametrize("drop", ["sig", "expires", "by"])
def test_an_incomplete_link_is_refused(drop: str):
    with pytest.raises(PermissionDeniedError, match="not a complete signed link"):
        links.verify(KEYS, RUN, [p for p in _signed() if p[0] != drop], NOW)


def test_an_expired_link_is_refused():
    signed = _signed(dt.timedelta(seconds=60))
    assert links.verify(KEYS, RUN, signed, NOW + dt.timedelta(seconds=59)) == "token-1"
    with pytest.raises(PermissionDeniedError, match="expired at 2030-01-02T03:05:05Z"):
        links.verify(KEYS, RUN, signed, NOW + dt.timedelta(seconds=60))


def test_the_path_quotes_the_run_and_its_parameters():
    path = links.recording_path("run 1/x", [("include", "/world/**")])
    assert path == "/v1/runs/run%201%2Fx/recording.rrd?include=%2Fworld%2F%2A%2A"


def test_a_link_reads_for_its_token_until_that_token_is_revoked(auth: Auth):
    issued = auth.issue(subject="alice", scopes=["read"], created_by="admin")
    reader = auth.authenticate(issued.token, "rest")
    expires = auth.clock() + dt.timedelta(hours=1)
    path = auth.sign_link(reader, RUN, PARAMS, expires)
    signed = links.sign(KEYS, RUN, PARAMS, expires.replace(microsecond=0), issued.record.id)
    assert path == links.recording_path(RUN, signed)

    principal = auth.link_principal(RUN, signed)
    assert principal.scopes == {Scope.READ} and principal.robot is None
    assert principal.token_id == issued.record.id and "alice" in principal.subject

    auth.revoke(issued.record.id, "admin")
    before = auth.failures[("link", FORBIDDEN)]
    with pytest.raises(PermissionDeniedError, match="revoked"):
        auth.link_principal(RUN, signed)
    with pytest.raises(PermissionDeniedError, match="signature"):
        auth.link_principal("run-2", signed)
    assert auth.failures[("link", FORBIDDEN)] == before + 2


def test_a_link_of_an_unknown_token_is_refused(auth: Auth):
    signed = links.sign(KEYS, RUN, PARAMS, auth.clock() + dt.timedelta(hours=1), "no-such-token")
    with pytest.raises(PermissionDeniedError):
        auth.link_principal(RUN, signed)


def test_with_auth_off_a_link_is_the_plain_url():
    off = Auth(enabled=False, keys=None, catalog=None)
    path = off.sign_link(off.authenticate(None, "rest"), RUN, PARAMS, NOW)
    assert path == links.recording_path(RUN, PARAMS) and "sig=" not in path


@pytest.mark.parametrize("signature", ["é" * 64, "\u00b2", ""])
def test_a_signature_that_is_not_hex_is_refused(signature: str):
    signed = [(k, signature if k == "sig" else v) for k, v in _signed()]
    with pytest.raises(PermissionDeniedError, match="signature does not match"):
        links.verify(KEYS, RUN, signed, NOW)


def test_a_link_ends_when_the_token_that_signed_it_expires(auth: Auth):
    issued = auth.issue(subject="alice", scopes=["read"], created_by="admin", expires_in=dt.timedelta(hours=1))
    signed = links.sign(KEYS, RUN, PARAMS, auth.clock() + dt.timedelta(days=7), issued.record.id)
    assert auth.link_principal(RUN, signed).token_id == issued.record.id
    later = auth.clock() + dt.timedelta(hours=2)
    auth.clock = lambda: later
    with pytest.raises(PermissionDeniedError, match="expired"):
        auth.link_principal(RUN, signed)
