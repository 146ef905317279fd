"""The web console's login: a token given once at the login form becomes a session cookie.

The cookie is not the token: it is a JWT of its own (audience `fleet-console`, so no API accepts it
as a bearer token) naming the token's id, valid for `SESSION_TTL` or until the token expires,
whichever comes first. Each request looks the token up again (cached as API tokens are), so revoking
the token ends its console sessions too, and looks the session up among those ended by logging out
(in the catalog, so a logout ends the session on every node at once). Actions carry a CSRF value
derived from the session with the depot's key, checked on every form post.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import uuid

import jwt

from catalog.db import session_scope
from catalog.sessions import end_session, session_ended
from core.errors import PermissionDeniedError, UnauthenticatedError
from services.auth.scopes import Principal, Scope, local_principal
from services.auth.tokens import INVALID, ISSUER, PEER_AUDIENCE, Auth

CONSOLE_AUDIENCE = "fleet-console"
SESSION_TTL = dt.timedelta(hours=12)
_ALGORITHM = "HS256"
_CSRF_CONTEXT = b"fleet console csrf v1"


def open_session(auth: Auth, token: str) -> tuple[str | None, Principal]:
    """The session cookie for a token typed at the login form, and who it stands for. The cookie is
    None with auth off (everyone is the local principal). UNAUTHENTICATED for a token the depot does
    not accept; PERMISSION_DENIED for one that reads nothing (a robot's ingest token)."""
    if not auth.enabled:
        return None, local_principal()
    principal = auth.authenticate(token.strip(), "console")
    if principal.token_id is None or auth.claims(token.strip()).get("aud") == PEER_AUDIENCE:
        raise UnauthenticatedError(
            "this is not a token for people: log in with a token from fleet tokens create", INVALID
        )
    if not principal.allows(Scope.READ):
        raise PermissionDeniedError(
            "this token reads nothing (a robot's ingest token): log in with a read, write or admin token"
        )
    assert auth.keys is not None
    record = auth.standing(principal.token_id)
    now = auth.clock()
    ends = now + SESSION_TTL
    if record is not None and record.expires_at is not None:
        ends = min(ends, record.expires_at)
    claims = {
        "iss": ISSUER,
        "aud": CONSOLE_AUDIENCE,
        "sub": principal.subject,
        "tid": principal.token_id,
        "jti": uuid.uuid4().hex,
        "iat": int(now.timestamp()),
        "exp": int(ends.timestamp()),
    }
    key = auth.keys.current
    return jwt.encode(claims, key.secret, _ALGORITHM, {"kid": key.id}), principal


def session_principal(auth: Auth, cookie: str | None) -> Principal | None:
    """Who a console session cookie stands for; None if there is no valid session (log in again):
    absent, tampered with, expired, or its token revoked or expired since."""
    if not auth.enabled:
        return local_principal()
    claims = _session_claims(auth, cookie)
    if claims is None or _ended(auth, str(claims["jti"])):
        return None
    record = auth.standing(str(claims["tid"]))
    if record is None or record.revoked_at is not None:
        return None
    if record.expires_at is not None and record.expires_at <= auth.clock():
        return None
    scopes = frozenset(Scope(s) for s in record.scopes)
    return Principal(record.subject, scopes, record.robot_id, record.id, record.expires_at)


def close_session(auth: Auth, cookie: str | None) -> None:
    """Log out: the session of `cookie` ends on every node, though its cookie is still signed and
    unexpired (a copy of it, kept or stolen, is refused from now on). Nothing to do for a cookie
    that is no valid session anyway, or with auth off."""
    if not auth.enabled or auth.catalog is None:
        return
    claims = _session_claims(auth, cookie)
    if claims is None:
        return
    expires_at = dt.datetime.fromtimestamp(int(str(claims["exp"])), dt.UTC)
    with session_scope(auth.catalog, write=True) as session:
        end_session(session, str(claims["jti"]), str(claims["tid"]), expires_at, auth.clock())


def _ended(auth: Auth, session_id: str) -> bool:
    """Whether the session was ended by logging out: asked of the catalog on each request (a lookup
    by primary key), so a logout counts on every node at once."""
    assert auth.catalog is not None
    with session_scope(auth.catalog) as session:
        return session_ended(session, session_id)


def csrf_value(auth: Auth, cookie: str | None, fallback: str) -> str:
    """The CSRF value a session's forms carry: bound to the session (its id, with the depot's key),
    or with auth off to `fallback` (a random value kept in a SameSite cookie of its own)."""
    claims = _session_claims(auth, cookie) if auth.enabled else None
    if claims is None or auth.keys is None:
        return fallback
    return hmac.new(auth.keys.current.secret, _CSRF_CONTEXT + str(claims["jti"]).encode(), hashlib.sha256).hexdigest()


def _session_claims(auth: Auth, cookie: str | None) -> dict[str, object] | None:
    if not cookie or auth.keys is None:
        return None
    try:
        key = auth.keys.by_id(jwt.get_unverified_header(cookie).get("kid"))
        if key is None:
            return None
        claims: dict[str, object] = jwt.decode(
            cookie,
            key.secret,
            algorithms=[_ALGORITHM],
            audience=CONSOLE_AUDIENCE,
            issuer=ISSUER,
            options={"require": ["exp", "jti", "tid"], "verify_iat": False},
        )
    except jwt.InvalidTokenError:
        return None
    return claims
