"""Hostile input to the dataset routes (auth on, on each catalog): selections with every field of
the wrong type, size or range, bodies that are no JSON, hostile names, versions and cursors, and
hypothesis-made selections. Every answer is 2xx or 4xx with a code and a message, never a 5xx; the
depot keeps what it had (`assert_intact`), and a version made before the attack is unchanged."""

from __future__ import annotations

import copy
from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from tests.services.corpus.test_hostile import BIG, FUZZ, HOSTILE_TEXTS, Attacker, attacker, depot

__all__ = ["attacker", "depot"]  # the fixtures of the corpus's hostile suite, used here by name

BASE: dict[str, Any] = {"name": "drives", "include": ["/**"], "timeline": "log_time"}
WRONG: list[Any] = [None, [], {}, "x", "", True, 1.5, -1, 2**63, 10**400, "\x00", "x" * 100_000, *HOSTILE_TEXTS[:8]]
FIELDS = [
    "name", "robot", "application", "since", "until", "status", "tier", "entity", "properties", "metric", "tag",
    "event", "event_window", "include", "exclude", "timeline", "fps", "split", "seed",
]  # fmt: skip


def create(attacker: Attacker, body: Any) -> int:
    return attacker.send("POST", "/v1/datasets", json=body).status_code


def test_every_selection_field_of_the_wrong_kind_is_refused_never_a_500(attacker: Attacker) -> None:
    made = attacker.send("POST", "/v1/datasets", json=BASE)
    assert made.status_code == 201, made.text
    before = attacker.send("GET", "/v1/datasets/drives/1").json()
    for field in FIELDS:
        for value in WRONG:
            status = create(attacker, {**copy.deepcopy(BASE), field: value})
            assert status in (201, 422), f"{field} = {str(value)[:60]}: {status}"
    for window in ({"event": ["x"], "before_s": -1}, {"event": [], "before_s": 1}, {"event": ["x"], "after_s": 1e309},
                   {"event": ["x"], "before_s": 4000}, {"event": ["x"], "extra": 1}):  # fmt: skip
        assert create(attacker, {**BASE, "event_window": window}) == 422, window
    for split in ({"train": 0.5}, {"train": 0.9, "val": 0.2}, {"Train": 1.0}, {"": 1.0}, {"a" * 40: 1.0}, {"t": -1}):
        assert create(attacker, {**BASE, "split": split}) == 422, split
    for fps in [0, -1, 1001, *BIG]:
        assert create(attacker, {**BASE, "fps": fps}) == 422, fps
    assert attacker.send("GET", "/v1/datasets/drives/1").json() == before  # versions are immutable


def test_bodies_that_are_no_selection_and_hostile_names(attacker: Attacker) -> None:
    for content in (b"", b"{", b"null", b"[" * 50_000 + b"]" * 50_000, b"\xff\xfe", b'{"name": NaN}'):
        answer = attacker.send("POST", "/v1/datasets", content=content)
        assert answer.status_code in (400, 415, 422), content[:40]
    for name in ("no-such", "..%2F..%2Fetc", "a" * 5000, "%00", "' OR 1=1 --"):
        assert attacker.send("GET", f"/v1/datasets/{name}").status_code in (404, 422), name
        for version in ("1", "0", "-1", "x", str(2**63), "1e3"):
            assert attacker.send("GET", f"/v1/datasets/{name}/{version}").status_code in (404, 422), (name, version)
    attacker.send("POST", "/v1/datasets", json=BASE)
    for cursor in ("x", "%00", "a" * 10_000, "eyJ4IjoxfQ"):
        status = attacker.send("GET", "/v1/datasets/drives/1", params={"cursor": cursor}).status_code
        assert status == 422, cursor


@FUZZ
@given(
    changes=st.dictionaries(
        st.sampled_from(FIELDS),
        st.one_of(
            st.text(max_size=60),
            st.integers(),
            st.floats(),
            st.none(),
            st.lists(st.text(max_size=30), max_size=3),
            st.dictionaries(st.text(max_size=10), st.one_of(st.floats(), st.text(max_size=10)), max_size=3),
        ),
        max_size=4,
    )
)
def test_any_selection_is_resolved_or_refused(attacker: Attacker, changes: dict[str, Any]) -> None:
    assert create(attacker, {**BASE, **changes}) in (201, 422)
