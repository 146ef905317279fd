"""The depot's tokens: JWTs it signs (HS256, PyJWT), each recorded in the catalog by its id so it
can be listed and revoked; the token itself is never stored.

Claims: `sub` (who acts), `scope` (space-separated), `robot` (an ingest token's robot), `jti`,
`iat`, `exp`, plus what Rerun's viewer and SDK read before they send a token to a server: `iss`,
`aud`, `permissions` and `allowed_hosts` (they send it only to hosts named there, and only a JWT
with all of iss, sub, aud, exp and iat; so a token "without expiry" carries a distant `exp`).
"""

from __future__ import annotations

import datetime as dt
import logging
import socket
import threading
import uuid
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import jwt
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import session_scope
from catalog.tokens import TokenRecord, add_token, revoke_token, token_record, token_records
from core.clock import iso_utc, utcnow
from core.errors import InvalidArgumentError, PermissionDeniedError, UnauthenticatedError
from core.ids import check_id
from services.auth import links
from services.auth.keys import SigningKeys
from services.auth.scopes import Principal, Scope, local_principal, parse_scopes
from services.auth.token_cache import WAIT_S, TokenCache

log = logging.getLogger(__name__)

ISSUER = "fleet-telemetry"
AUDIENCE = "redap"  # what Rerun's clients expect of a catalog server's token
PEER_AUDIENCE = "fleet-peer"  # a node's own short-lived token, handing chunks to another node
PEER_TOKEN_TTL = dt.timedelta(minutes=5)
NO_EXPIRY = dt.timedelta(days=365 * 100)
_ALGORITHM = "HS256"
MAX_NAME = 256

# Reasons a request is refused, as counted in /metrics (fleet_auth_failures_total{reason=...}).
MISSING, INVALID, EXPIRED, REVOKED, FORBIDDEN = "missing", "invalid", "expired", "revoked", "forbidden"


def default_hosts() -> list[str]:
    """Where a depot is reached when nobody said: loopback and this machine's names."""
    hosts = ["localhost", "127.0.0.1", socket.gethostname(), socket.getfqdn()]
    return list(dict.fromkeys(h for h in hosts if h))


@dataclass(frozen=True)
class IssuedToken:
    token: str  # shown once, to whoever asked for it; never stored
    record: TokenRecord
    allowed_hosts: list[str]


class Auth:
    """Issues and checks tokens. With `enabled` False (auth off on a loopback bind) every caller is
    the local principal and nothing is checked."""

    def __init__(
        self,
        *,
        enabled: bool,
        keys: SigningKeys | None,
        catalog: sessionmaker[Session] | None,
        public_hosts: list[str] | None = None,
        cache_s: float = 5.0,
        stale_s: float = 600.0,
        catalog_wait_s: float = WAIT_S,
        clock: Callable[[], dt.datetime] = utcnow,
    ) -> None:
        if enabled and (keys is None or catalog is None):
            raise ValueError("auth needs signing keys and a catalog")
        self.enabled = enabled
        self.keys = keys
        self.catalog = catalog
        self.public_hosts = public_hosts or default_hosts()
        self.cache_s = cache_s
        self.clock = clock
        self.failures: Counter[tuple[str, str]] = Counter()  # (surface, reason) -> refusals
        self._known = TokenCache(self._catalog_record, fresh_s=cache_s, stale_s=stale_s, wait_s=catalog_wait_s)
        self._lock = threading.Lock()

    # --- checking ---------------------------------------------------------------------------

    def authenticate(self, token: str | None, surface: str) -> Principal:
        """The principal `token` stands for; UNAUTHENTICATED (counted per surface and reason) if it
        stands for none. Asks the catalog at most every `cache_s` per token: call off the event loop."""
        if not self.enabled:
            return local_principal()
        try:
            return self._principal(token, surface)
        except UnauthenticatedError as exc:
            self.refused(surface, exc.reason)
            raise

    def authorize(self, principal: Principal, surface: str, *scopes: Scope) -> Principal:
        """`principal`, if it holds one of `scopes`; else PERMISSION_DENIED, counted for `surface`."""
        try:
            return principal.require(*scopes)
        except PermissionDeniedError:
            self.refused(surface, FORBIDDEN)
            raise

    def refused(self, surface: str, reason: str) -> None:
        with self._lock:
            self.failures[(surface, reason)] += 1

    def _principal(self, token: str | None, surface: str) -> Principal:
        if not token:
            how = "`authorization: Bearer TOKEN` metadata" if surface == "grpc" else "`Authorization: Bearer TOKEN`"
            raise UnauthenticatedError(
                f"no token: send {how} (the CLI reads FLEET_TOKEN; an admin creates tokens with fleet tokens create)",
                MISSING,
            )
        claims = self.claims(token)
        if claims.get("aud") == PEER_AUDIENCE:  # signed by a node with the depot's key: no catalog record
            robot = claims.get("robot")
            scopes = frozenset(
                Scope(s) for s in str(claims.get("scope", "")).split() if s in Scope.__members__.values()
            )
            return Principal(str(claims["sub"]), scopes, str(robot) if robot else None)
        record = self._record(str(claims["jti"]))
        if record is None:
            raise UnauthenticatedError(
                "this token is not in the depot's catalog (signed with this depot's key, but not listed); "
                "ask an admin for a new one",
                INVALID,
            )
        if record.revoked_at is not None:
            raise UnauthenticatedError(
                f"token {record.id} was revoked at {iso_utc(record.revoked_at)}; ask an admin for a new one",
                REVOKED,
            )
        scopes = frozenset(Scope(s) for s in record.scopes)
        return Principal(record.subject, scopes, record.robot_id, record.id, record.expires_at)

    def link_principal(self, run_id: str, params: list[tuple[str, str]]) -> Principal:
        """Who a signed link stands for: read access to its run with its parameters, as long as the
        link is intact, not expired, and the token that signed it is not revoked (403 otherwise)."""
        if not self.enabled:
            return local_principal()
        assert self.keys is not None
        try:
            by = links.verify(self.keys, run_id, params, self.clock())
            record = self._record(by)
            if record is None or record.revoked_at is not None:
                raise PermissionDeniedError("the token that signed this link was revoked: ask for a new link")
            if record.expires_at is not None and record.expires_at <= self.clock():
                raise PermissionDeniedError("the token that signed this link has expired: ask for a new link")
        except PermissionDeniedError:
            self.refused("link", FORBIDDEN)
            raise
        ends = min(t for t in (links.expires_at(params), record.expires_at) if t is not None)
        return Principal(f"link from {record.subject}", frozenset({Scope.READ}), None, record.id, ends)

    def sign_link(
        self, principal: Principal, run_id: str, params: list[tuple[str, str]], expires_at: dt.datetime
    ) -> str:
        """The path and query of a signed link to a run's recording with `params`."""
        if not self.enabled or self.keys is None or principal.token_id is None:
            return links.recording_path(run_id, params)  # auth off: the plain URL opens it
        return links.recording_path(run_id, links.sign(self.keys, run_id, params, expires_at, principal.token_id))

    def claims(self, token: str) -> dict[str, object]:
        """The claims of a token this depot signed with one of its keys, not expired."""
        assert self.keys is not None
        try:
            key = self.keys.by_id(jwt.get_unverified_header(token).get("kid"))
            if key is None:
                raise UnauthenticatedError(
                    "this token was not signed by this depot (an unknown key; after a key rotation, "
                    "add the old key to FLEET_AUTH_PREVIOUS_KEYS until its tokens are replaced)",
                    INVALID,
                )
            claims: dict[str, object] = jwt.decode(
                token,
                key.secret,
                algorithms=[_ALGORITHM],
                audience=[AUDIENCE, PEER_AUDIENCE],
                issuer=ISSUER,
                # `iat` is not checked against this node's clock: a token made a moment ago on a
                # node whose clock is a little ahead is not "from the future" here. `exp` is.
                options={"require": ["exp", "iat", "jti", "sub"], "verify_iat": False},
            )
        except jwt.ExpiredSignatureError:
            raise UnauthenticatedError("this token has expired; ask an admin for a new one", EXPIRED) from None
        except jwt.InvalidTokenError as exc:
            raise UnauthenticatedError(
                f"this is not a valid token of this depot ({type(exc).__name__}); check that it was copied whole",
                INVALID,
            ) from None
        return claims

    def standing(self, token_id: str) -> TokenRecord | None:
        """A token's catalog record (revoked or not), asked of the catalog at most every `cache_s`
        (`TokenCache`: within `stale_s` while it does not answer); None if the catalog does not list
        it. Call off the event loop."""
        return self._record(token_id)

    def _record(self, token_id: str) -> TokenRecord | None:
        return self._known.get(token_id)

    def _catalog_record(self, token_id: str) -> TokenRecord | None:
        assert self.catalog is not None
        with session_scope(self.catalog) as session:
            return token_record(session, token_id)

    # --- issuing, listing, revoking -----------------------------------------------------------

    def peer_token(self, node_id: str, robot: str | None, scopes: Iterable[Scope] = (Scope.WRITE,)) -> str | None:
        """A short-lived token of this node for another node of the depot: to hand it a hot copy of
        `robot`'s run (write scope, bound to that robot if known), or to ask it, for a caller this
        node has checked, what that caller may ask (the caller's scopes and robot). None with auth
        off. Kept nowhere."""
        if not self.enabled or self.keys is None:
            return None
        now = self.clock()
        claims: dict[str, object] = {
            "iss": ISSUER,
            "aud": PEER_AUDIENCE,
            "sub": f"node:{node_id}",
            "jti": uuid.uuid4().hex,
            "iat": int(now.timestamp()),
            "exp": int((now + PEER_TOKEN_TTL).timestamp()),
            "scope": " ".join(sorted(s.value for s in scopes)),
        }
        if robot is not None:
            claims["robot"] = robot
        return jwt.encode(claims, self.keys.current.secret, _ALGORITHM, {"kid": self.keys.current.id})

    def issue(
        self,
        *,
        subject: str,
        scopes: list[str] | tuple[str, ...],
        created_by: str,
        robot: str | None = None,
        name: str | None = None,
        expires_in: dt.timedelta | None = None,
        hosts: list[str] | None = None,
    ) -> IssuedToken:
        """Sign a new token and record its id; the token is returned once and kept nowhere."""
        if self.keys is None or self.catalog is None:
            raise InvalidArgumentError("auth is off on this depot (FLEET_AUTH=off): it issues no tokens")
        granted = parse_scopes(scopes)
        robot = _robot_of(granted, robot)
        if not subject.strip():
            raise InvalidArgumentError("a token needs a name: who acts with it (--name alice), or its robot (--robot)")
        subject = _text("name", subject)
        if expires_in is not None and expires_in <= dt.timedelta(0):
            raise InvalidArgumentError("a token's lifetime must be positive (for example 90d, 12h, 30m)")
        now = self.clock().replace(microsecond=0)
        record = TokenRecord(
            id=uuid.uuid4().hex,
            name=_text("name", name or f"{' '.join(granted)} for {subject}"),
            subject=subject,
            scopes=tuple(s.value for s in granted),
            robot_id=robot,
            created_at=now,
            created_by=created_by[:MAX_NAME],
            expires_at=now + expires_in if expires_in is not None else None,
        )
        allowed = [_host(h) for h in hosts] if hosts else self.public_hosts
        token = jwt.encode(
            self._claims(record, allowed), self.keys.current.secret, _ALGORITHM, {"kid": self.keys.current.id}
        )
        with session_scope(self.catalog, write=True) as session:
            add_token(session, record)
        log.info("token %s (%s) created for %s by %s", record.id, " ".join(record.scopes), subject, created_by)
        return IssuedToken(token, record, allowed)

    def _claims(self, record: TokenRecord, allowed_hosts: list[str]) -> dict[str, object]:
        expires = record.expires_at or record.created_at + NO_EXPIRY
        claims: dict[str, object] = {
            "iss": ISSUER,
            "aud": AUDIENCE,
            "sub": record.subject,
            "jti": record.id,
            "iat": int(record.created_at.timestamp()),
            "exp": int(expires.timestamp()),
            "scope": " ".join(record.scopes),
            "permissions": _rerun_permissions(record.scopes),
            "allowed_hosts": allowed_hosts,
        }
        if record.robot_id is not None:
            claims["robot"] = record.robot_id
        return claims

    def tokens(self, *, include_revoked: bool = False) -> list[TokenRecord]:
        if self.catalog is None:
            return []
        with session_scope(self.catalog) as session:
            return token_records(session, include_revoked=include_revoked)

    def revoke(self, token_id: str, actor: str) -> TokenRecord:
        if self.catalog is None:
            raise InvalidArgumentError("auth is off on this depot (FLEET_AUTH=off): it has no tokens")
        with session_scope(self.catalog, write=True) as session:
            record = revoke_token(session, token_id, self.clock(), actor)
        self._known.forget(token_id)  # this node sees it at once; others within cache_s
        log.info("token %s revoked by %s", token_id, actor)
        return record


def _robot_of(scopes: tuple[Scope, ...], robot: str | None) -> str | None:
    if Scope.INGEST in scopes:
        if not robot:
            raise InvalidArgumentError("an ingest token is bound to one robot: give its id (--robot ROBOT)")
        return check_id("robot id", robot)
    if robot:
        raise InvalidArgumentError("only an ingest token is bound to a robot: add --scope ingest, or drop --robot")
    return None


def _text(what: str, value: str) -> str:
    value = value.strip()
    if not value or len(value) > MAX_NAME or not value.isprintable():
        raise InvalidArgumentError(f"a token's {what} must be 1 to {MAX_NAME} printable characters")
    return value


def _host(host: str) -> str:
    host = host.strip().lower()
    if not host or len(host) > 253 or not all(c.isalnum() or c in ".-:[]*" for c in host):
        raise InvalidArgumentError(f"{host!r} is not a host name for allowed_hosts (e.g. depot.example.com, 10.0.0.5)")
    return host


def _rerun_permissions(scopes: tuple[str, ...]) -> list[str]:
    """What Rerun's clients show: read, or read and write (they decide nothing with it)."""
    if Scope.WRITE in scopes or Scope.ADMIN in scopes:
        return ["read", "read-write"]
    return ["read"] if Scope.READ in scopes else []


def token_answer(record: TokenRecord) -> dict[str, object]:
    """A token's record as the API shows it (never the token)."""
    return {
        "id": record.id,
        "name": record.name,
        "subject": record.subject,
        "scopes": list(record.scopes),
        "robot": record.robot_id,
        "created_at": iso_utc(record.created_at),
        "created_by": record.created_by,
        "expires_at": iso_utc(record.expires_at),
        "revoked_at": iso_utc(record.revoked_at),
        "revoked_by": record.revoked_by,
    }
