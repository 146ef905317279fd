"""Scopes, and the principal a request acts as."""

from __future__ import annotations

import datetime as dt
import enum
from dataclasses import dataclass

from core.errors import InvalidArgumentError, PermissionDeniedError


class Scope(enum.StrEnum):
    INGEST = "ingest"  # stream and upload the runs of one robot (the token's)
    READ = "read"  # list, download, SQL, catalog browse, metrics
    WRITE = "write"  # upload for any robot, pin, restore, promote
    ADMIN = "admin"  # delete, retention runs, catalog rebuild, tokens


# What each scope grants besides itself: an admin can do what a writer can, a writer can read.
# Ingest grants nothing else: a robot's token reads nothing, not even its own runs.
_IMPLIES: dict[Scope, frozenset[Scope]] = {
    Scope.INGEST: frozenset(),
    Scope.READ: frozenset(),
    Scope.WRITE: frozenset({Scope.READ}),
    Scope.ADMIN: frozenset({Scope.WRITE, Scope.READ}),
}


def parse_scopes(names: list[str] | tuple[str, ...]) -> tuple[Scope, ...]:
    """Scope names as given (repeated, in any order) -> sorted unique scopes; one clear error else."""
    scopes = set()
    for name in names:
        try:
            scopes.add(Scope(name.strip().lower()))
        except ValueError:
            raise InvalidArgumentError(f"{name!r} is not a scope: use {', '.join(s.value for s in Scope)}") from None
    if not scopes:
        raise InvalidArgumentError(f"a token needs at least one scope: {', '.join(s.value for s in Scope)}")
    return tuple(sorted(scopes))


@dataclass(frozen=True)
class Principal:
    """Who a request acts as: a token's subject and what it grants."""

    subject: str
    scopes: frozenset[Scope]
    robot: str | None = None  # an ingest token's robot: the only robot it writes runs for
    token_id: str | None = None  # None when auth is off
    # When what it grants ends even if nothing is revoked: its token's expiry, or a signed link's
    # own (whichever comes first). None: no end of its own.
    expires_at: dt.datetime | None = None

    @property
    def granted(self) -> frozenset[Scope]:
        return self.scopes.union(*(_IMPLIES[s] for s in self.scopes))

    def allows(self, scope: Scope) -> bool:
        return scope in self.granted

    def require(self, *scopes: Scope) -> Principal:
        """This principal, if it holds one of `scopes`; else PERMISSION_DENIED naming them."""
        if any(self.allows(s) for s in scopes):
            return self
        needed = " or ".join(f"{s.value!r}" for s in scopes)
        has = ", ".join(sorted(s.value for s in self.scopes)) or "none"
        raise PermissionDeniedError(
            f"this needs the {needed} scope; the token of {self.subject!r} has {has} "
            "(an admin creates one with fleet tokens create --scope ...)"
        )

    @property
    def rate_key(self) -> str:
        """What rate limits count against: the token (all requests with it), else the subject."""
        return self.token_id or self.subject


def local_principal(subject: str = "local") -> Principal:
    """Everyone, when auth is off (a loopback bind): every scope, no robot binding."""
    return Principal(subject, frozenset(Scope) - {Scope.INGEST})
