"""Tokens: signed, recorded by id only, checked on every use (signature, expiry, catalog record,
revocation), with the claims Rerun's viewer and SDK look for."""

from __future__ import annotations

import base64
import datetime as dt
import json
import time
import uuid
from pathlib import Path

import jwt
import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import session_scope
from core.errors import InvalidArgumentError, NotFoundError, UnauthenticatedError
from services.auth.scopes import Scope
from services.auth.tokens import AUDIENCE, EXPIRED, INVALID, ISSUER, MISSING, NO_EXPIRY, REVOKED, Auth
from tests.services.auth.conftest import HOSTS, KEYS, OTHER_KEYS
from tests.waiting import wait_for


def _refused(auth: Auth, token: str | None, reason: str) -> str:
    before = auth.failures[("rest", reason)]
    with pytest.raises(UnauthenticatedError) as refused:
        auth.authenticate(token, "rest")
    assert refused.value.reason == reason
    assert auth.failures[("rest", reason)] == before + 1  # counted for /metrics
    assert "\n" not in refused.value.message and refused.value.http_status() == 401
    return refused.value.message


def test_an_issued_token_authenticates_as_its_subject(auth: Auth):
    issued = auth.issue(subject="alice", scopes=["write", "read"], created_by="admin")
    principal = auth.authenticate(issued.token, "rest")
    assert principal.subject == "alice" and principal.scopes == {Scope.READ, Scope.WRITE}
    assert principal.token_id == issued.record.id and principal.robot is None
    assert [t.id for t in auth.tokens()] == [issued.record.id]


def test_an_ingest_token_is_bound_to_its_robot(auth: Auth):
    issued = auth.issue(subject="robot-a", scopes=["ingest"], robot="robot-a", created_by="admin")
    assert auth.authenticate(issued.token, "grpc").robot == "robot-a"
    assert auth.claims(issued.token)["robot"] == "robot-a"
    with pytest.raises(InvalidArgumentError, match="--robot"):
        auth.issue(subject="robot-a", scopes=["ingest"], created_by="admin")
    with pytest.raises(InvalidArgumentError, match="only an ingest token"):
        auth.issue(subject="alice", scopes=["read"], robot="robot-a", created_by="admin")


def test_claims_carry_what_rerun_clients_look_for(auth: Auth):
    before = int(time.time())
    token = auth.issue(subject="alice", scopes=["read"], created_by="admin").token
    claims = jwt.decode(token, options={"verify_signature": False})
    assert claims["iss"] == ISSUER and claims["aud"] == AUDIENCE == "redap" and claims["sub"] == "alice"
    assert claims["allowed_hosts"] == HOSTS
    assert claims["permissions"] == ["read"] and claims["scope"] == "read"
    never = before + NO_EXPIRY.total_seconds()
    assert never - 5 <= claims["exp"] <= never + 5  # "never": a distant exp, since Rerun needs one
    assert before - 1 <= claims["iat"] <= before + 5
    assert jwt.get_unverified_header(token)["kid"] == KEYS.current.id

    writer = jwt.decode(
        auth.issue(subject="bob", scopes=["write"], created_by="admin", hosts=["viewer.example"]).token,
        options={"verify_signature": False},
    )
    assert writer["permissions"] == ["read", "read-write"] and writer["allowed_hosts"] == ["viewer.example"]
    lasting = auth.issue(subject="carol", scopes=["read"], created_by="admin", expires_in=dt.timedelta(hours=2))
    assert abs(int(str(auth.claims(lasting.token)["exp"])) - (before + 7200)) <= 5


def test_no_token_and_garbage_are_refused(auth: Auth):
    assert "Authorization: Bearer" in _refused(auth, None, MISSING)
    assert "not a valid token" in _refused(auth, "not-a-jwt", INVALID)
    unsigned = jwt.encode({"sub": "alice"}, key="", algorithm="none")
    _refused(auth, unsigned, INVALID)


def test_an_expired_token_is_refused(auth: Auth, catalog: sessionmaker[Session]):
    """PyJWT checks `exp` against the real time: the token is issued by a node whose clock is hours behind."""
    behind = Auth(
        enabled=True,
        keys=KEYS,
        catalog=catalog,
        clock=lambda: dt.datetime.now(dt.UTC) - dt.timedelta(hours=3),
    )
    issued = behind.issue(subject="alice", scopes=["read"], created_by="admin", expires_in=dt.timedelta(hours=1))
    assert "expired" in _refused(auth, issued.token, EXPIRED)


def test_a_token_from_a_node_whose_clock_is_ahead_is_accepted(auth: Auth, catalog: sessionmaker[Session]):
    """Nodes' clocks differ a little: a token used at once on another node is not "from the future"."""
    ahead = Auth(
        enabled=True, keys=KEYS, catalog=catalog, clock=lambda: dt.datetime.now(dt.UTC) + dt.timedelta(seconds=30)
    )
    issued = ahead.issue(subject="alice", scopes=["read"], created_by="admin")
    assert auth.authenticate(issued.token, "rest").subject == "alice"


def test_a_token_signed_with_another_key_is_refused(auth: Auth, catalog: sessionmaker[Session]):
    elsewhere = Auth(enabled=True, keys=OTHER_KEYS, catalog=catalog)
    token = elsewhere.issue(subject="alice", scopes=["admin"], created_by="admin").token
    assert "not signed by this depot" in _refused(auth, token, INVALID)
    # ... even when it names this depot's key id
    claims = jwt.decode(token, options={"verify_signature": False})
    forged = jwt.encode(claims, OTHER_KEYS.current.secret, "HS256", {"kid": KEYS.current.id})
    _refused(auth, forged, INVALID)


def test_a_tampered_payload_is_refused(auth: Auth):
    token = auth.issue(subject="alice", scopes=["read"], created_by="admin").token
    header, payload, signature = token.split(".")
    claims = json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))
    claims["scope"] = "admin"
    claims["sub"] = "root"
    forged = base64.urlsafe_b64encode(json.dumps(claims).encode()).rstrip(b"=").decode()
    _refused(auth, f"{header}.{forged}.{signature}", INVALID)
    middle = len(signature) // 2  # a character that carries six bits of the signature (the last ones may not)
    other = "A" if signature[middle] != "A" else "B"
    _refused(auth, f"{header}.{payload}.{signature[:middle]}{other}{signature[middle + 1 :]}", INVALID)


def test_a_token_signed_here_but_not_in_the_catalog_is_refused(auth: Auth):
    issued = auth.issue(subject="alice", scopes=["read"], created_by="admin")
    claims = jwt.decode(issued.token, options={"verify_signature": False})
    claims["jti"] = uuid.uuid4().hex
    unknown = jwt.encode(claims, KEYS.current.secret, "HS256", {"kid": KEYS.current.id})
    assert "not in the depot's catalog" in _refused(auth, unknown, INVALID)


def test_a_revoked_token_is_refused_at_once_on_the_node_that_revoked_it(auth: Auth):
    issued = auth.issue(subject="alice", scopes=["read"], created_by="admin")
    auth.authenticate(issued.token, "rest")  # cached now
    record = auth.revoke(issued.record.id, "admin")
    assert record.revoked_at is not None and record.revoked_by == "admin"
    assert issued.record.id in _refused(auth, issued.token, REVOKED)
    assert auth.tokens() == [] and [t.id for t in auth.tokens(include_revoked=True)] == [issued.record.id]
    assert auth.revoke(issued.record.id, "someone else").revoked_by == "admin"  # revoking again changes nothing
    with pytest.raises(NotFoundError, match="fleet tokens ls"):
        auth.revoke("no-such-token", "admin")


def test_other_nodes_see_a_revocation_within_cache_s(auth: Auth, catalog: sessionmaker[Session]):
    issued = auth.issue(subject="alice", scopes=["read"], created_by="admin")
    lasting = Auth(enabled=True, keys=KEYS, catalog=catalog, cache_s=3600)
    brief = Auth(enabled=True, keys=KEYS, catalog=catalog, cache_s=0.5)
    uncached = Auth(enabled=True, keys=KEYS, catalog=catalog, cache_s=0)
    for node in (lasting, brief, uncached):
        node.authenticate(issued.token, "rest")
    auth.revoke(issued.record.id, "admin")
    revoked_at = time.monotonic()
    _refused(uncached, issued.token, REVOKED)
    assert lasting.authenticate(issued.token, "rest").token_id == issued.record.id  # its cache still holds

    def refused_because() -> str | None:
        try:
            brief.authenticate(issued.token, "rest")
        except UnauthenticatedError as exc:
            return exc.reason
        return None

    left = revoked_at + 10 - time.monotonic()
    assert wait_for(refused_because, left, "the revocation seen within cache_s", interval=0.05) == REVOKED


def test_the_token_is_never_stored(auth: Auth, catalog: sessionmaker[Session], fresh_catalog_url: str):
    tokens = [
        auth.issue(subject="alice", scopes=["admin"], created_by="admin").token,
        auth.issue(subject="robot-a", scopes=["ingest"], robot="robot-a", created_by="admin").token,
    ]
    auth.revoke(auth.tokens()[0].id, "admin")
    secrets = [piece for token in tokens for piece in (token, token.split(".")[2])]  # the whole, the signature
    with session_scope(catalog) as session:
        names = sa.inspect(session.get_bind()).get_table_names()
        rows = [str(tuple(row)) for name in names for row in session.execute(sa.text(f'SELECT * FROM "{name}"'))]
    assert any(auth.tokens(include_revoked=True)[0].id in row for row in rows)  # the ids are there
    for secret in secrets:
        assert not any(secret in row for row in rows)
    if fresh_catalog_url.startswith("duckdb:///"):
        catalog.kw["bind"].dispose()
        stored = Path(fresh_catalog_url.removeprefix("duckdb:///"))
        files = [p for p in stored.parent.iterdir() if p.name.startswith(stored.name)]  # the file and its log
        for secret in secrets:
            assert not any(secret.encode() in f.read_bytes() for f in files)


def test_auth_off_lets_everyone_in_and_issues_nothing():
    off = Auth(enabled=False, keys=None, catalog=None)
    assert off.authenticate(None, "rest").allows(Scope.ADMIN)
    with pytest.raises(InvalidArgumentError, match="FLEET_AUTH=off"):
        off.issue(subject="alice", scopes=["read"], created_by="admin")


@pytest.mark.parametrize(
    ("kwargs", "says"),
    [
        ({"subject": " ", "scopes": ["read"]}, "needs a name"),
        ({"subject": "a\nb", "scopes": ["read"]}, "printable"),
        ({"subject": "alice", "scopes": ["read"], "expires_in": dt.timedelta(0)}, "must be positive"),
        ({"subject": "alice", "scopes": ["sudo"]}, "not a scope"),
    ],
)
def test_bad_requests_for_tokens_are_one_clear_line(auth: Auth, kwargs, says):
    with pytest.raises(InvalidArgumentError, match=says):
        auth.issue(created_by="admin", **kwargs)
    assert auth.tokens() == []
