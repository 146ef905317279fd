"""The one backoff curve (core/backoff.py) promotion, catalog writes and the agent's link share."""

from __future__ import annotations

from core.backoff import backoff_delay, jittered


def test_the_wait_doubles_from_the_first_up_to_the_cap():
    waits = [backoff_delay(n, first=1.0, cap=300.0) for n in range(1, 12)]
    assert waits == [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 300.0, 300.0]
    assert [backoff_delay(n, first=0.25, cap=10.0) for n in (1, 2, 3, 6, 7)] == [0.25, 0.5, 1.0, 8.0, 10.0]


def test_no_wait_before_a_failure_and_no_overflow_after_many():
    assert backoff_delay(0, first=1.0, cap=300.0) == 0.0
    assert backoff_delay(10_000, first=2.0, cap=300.0) == 300.0


def test_jitter_stays_within_its_spread():
    assert jittered(10.0, uniform=lambda lo, hi: lo) == 8.0
    assert jittered(10.0, uniform=lambda lo, hi: hi) == 12.0
    assert all(9.0 <= jittered(10.0, spread=0.1) <= 11.0 for _ in range(200))
