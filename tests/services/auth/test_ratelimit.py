"""Per-token rate limits: each token its own share, 429 with Retry-After past it, nothing counted
without a token (auth off)."""

from __future__ import annotations

import pytest

from core.errors import RateLimitedError
from services.auth.ratelimit import RateLimits
from services.auth.scopes import Principal, Scope, local_principal


def _token(token_id: str) -> Principal:
    return Principal("alice", frozenset({Scope.READ}), None, token_id)


def test_a_token_past_its_share_is_told_when_to_retry():
    limits = RateLimits({"sql": "2/minute", "download": "5/minute"})
    alice = _token("t1")
    limits.hit("sql", alice)
    limits.hit("sql", alice)
    with pytest.raises(RateLimitedError) as refused:
        limits.hit("sql", alice)
    error = refused.value
    assert error.http_status() == 429
    assert 1 <= error.retry_after_s <= 60 and error.headers() == {"Retry-After": str(error.retry_after_s)}
    assert "too many sql requests" in error.message and "at most 2 per 1 minute" in error.message
    limits.hit("download", alice)  # another kind has its own share


def test_another_token_is_not_affected():
    limits = RateLimits({"sql": "1/minute"})
    limits.hit("sql", _token("t1"))
    with pytest.raises(RateLimitedError):
        limits.hit("sql", _token("t1"))
    limits.hit("sql", _token("t2"))


def test_nothing_is_limited_without_a_token():
    limits = RateLimits({"sql": "1/minute"})
    for _ in range(10):
        limits.hit("sql", local_principal())
