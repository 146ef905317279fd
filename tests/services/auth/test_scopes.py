"""Scopes: what each grants, and the one-line refusal naming the scope an action needs."""

from __future__ import annotations

import pytest

from core.errors import InvalidArgumentError, PermissionDeniedError
from services.auth.scopes import Principal, Scope, local_principal, parse_scopes


def _principal(*scopes: Scope, robot: str | None = None) -> Principal:
    return Principal("alice", frozenset(scopes), robot, "t1")


@pytest.mark.parametrize(
    ("held", "granted"),
    [
        (Scope.ADMIN, {Scope.ADMIN, Scope.WRITE, Scope.READ}),
        (Scope.WRITE, {Scope.WRITE, Scope.READ}),
        (Scope.READ, {Scope.READ}),
        (Scope.INGEST, {Scope.INGEST}),  # a robot's token reads nothing, not even its own runs
    ],
)
def test_each_scope_grants_itself_and_what_it_implies(held: Scope, granted: set[Scope]):
    principal = _principal(held)
    assert principal.granted == granted
    for scope in Scope:
        assert principal.allows(scope) is (scope in granted)


def test_no_scope_implies_ingest_or_admin():
    """Ingest binds a robot: only a token made for it holds it; admin is only given."""
    for held in Scope:
        implied = _principal(held).granted - {held}
        assert Scope.INGEST not in implied and Scope.ADMIN not in implied


def test_require_answers_the_principal_when_one_scope_is_held():
    principal = _principal(Scope.WRITE)
    assert principal.require(Scope.READ) is principal
    assert principal.require(Scope.INGEST, Scope.WRITE) is principal


@pytest.mark.parametrize(
    ("held", "needed", "named"),
    [
        ((Scope.READ,), (Scope.WRITE,), "'write'"),
        ((Scope.WRITE,), (Scope.ADMIN,), "'admin'"),
        ((Scope.INGEST,), (Scope.READ,), "'read'"),
        ((Scope.READ,), (Scope.INGEST, Scope.WRITE), "'ingest' or 'write'"),
    ],
)
def test_require_refuses_naming_the_scope_needed_and_the_scopes_held(held, needed, named):
    with pytest.raises(PermissionDeniedError) as refused:
        _principal(*held).require(*needed)
    message = refused.value.message
    assert f"needs the {named} scope" in message
    assert "'alice'" in message and ", ".join(sorted(s.value for s in held)) in message
    assert "fleet tokens create" in message and "\n" not in message
    assert refused.value.http_status() == 403


def test_parse_scopes_sorts_dedupes_and_ignores_case():
    assert parse_scopes([" Write", "read", "write"]) == (Scope.READ, Scope.WRITE)


@pytest.mark.parametrize(("names", "says"), [(["root"], "'root' is not a scope"), ([], "at least one scope")])
def test_parse_scopes_refuses_with_one_line(names, says):
    with pytest.raises(InvalidArgumentError, match=says) as refused:
        parse_scopes(names)
    assert "ingest, read, write, admin" in refused.value.message


def test_the_local_principal_may_do_anything_but_is_bound_to_no_robot():
    local = local_principal()
    assert all(local.allows(s) for s in (Scope.READ, Scope.WRITE, Scope.ADMIN))
    assert local.robot is None and local.token_id is None and local.rate_key == "local"
