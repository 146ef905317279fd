"""Hostile input to the trigger routes (auth on, on each catalog): a robot's trigger report
(`POST /v1/runs/RUN/triggered`) with every field replaced by values of the wrong type, size or
range, bodies that are no JSON, hostile run and event ids, and hypothesis-made reports; an event's
pull (`POST /v1/events/EVENT/pull`). Every answer is 2xx or 4xx with a code and a message, never a
5xx, and the depot keeps what it had (`assert_intact`)."""

from __future__ import annotations

import copy
from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from tests.services.corpus.test_hostile import BIG, FUZZ, HOSTILE_TEXTS, RUN, Attacker, attacker, depot

__all__ = ["attacker", "depot"]  # the fixtures of test_hostile.py, used here by name

T = 1_790_000_000_000_000_000
REPORT: dict[str, Any] = {
    "pull_id": "pull-0123456789ab",
    "rules_version": 1,
    "event": {
        "kind": "intervention",
        "severity": "warn",
        "timeline": "log_time",
        "timeline_type": "timestamp",
        "start": T,
        "end": T + 10,
        "label": "",
    },
    "window": {
        "timeline": "log_time",
        "start": str(T - 10),
        "end": str(T + 20),
        "include": ["/camera/**"],
        "exclude": [],
    },
    "priority": "high",
    "state": "sending",
    "chunks_sent": 0,
    "bytes_sent": 0,
    "error": None,
}
WRONG: list[Any] = [None, [], {}, "x", "", True, 1.5, -1, 2**63, 10**400, "\x00", "x" * 100_000, *HOSTILE_TEXTS[:8]]


def report(attacker: Attacker, body: Any, run: str = RUN) -> int:
    return attacker.send("POST", f"/v1/runs/{run}/triggered", json=body).status_code


def replaced(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    body = copy.deepcopy(REPORT)
    inner = body
    for key in path[:-1]:
        inner = inner[key]
    inner[path[-1]] = value
    return body


def test_a_valid_report_is_filed_and_its_resend_answers_the_same(attacker: Attacker) -> None:
    first = attacker.send("POST", f"/v1/runs/{RUN}/triggered", json=REPORT)
    again = attacker.send("POST", f"/v1/runs/{RUN}/triggered", json=REPORT)
    assert first.status_code in (200, 201) and again.status_code == 200, (first.text, again.text)
    assert first.json()["pull"]["id"] == again.json()["pull"]["id"] == REPORT["pull_id"]


def test_every_field_of_the_wrong_kind_is_refused_never_a_500(attacker: Attacker) -> None:
    fields = [
        ("pull_id",), ("rules_version",), ("priority",), ("state",), ("chunks_sent",), ("bytes_sent",), ("error",),
        ("event",), ("event", "kind"), ("event", "severity"), ("event", "timeline"), ("event", "timeline_type"),
        ("event", "start"), ("event", "end"), ("event", "label"),
        ("window",), ("window", "timeline"), ("window", "start"), ("window", "end"), ("window", "include"),
        ("window", "exclude"),
    ]  # fmt: skip
    for path in fields:
        for value in WRONG:
            status = report(attacker, replaced(path, value))
            assert status in (200, 201, 404, 409, 422), f"{path} = {str(value)[:60]}: {status}"
    for big in BIG:
        assert report(attacker, replaced(("event", "start"), big)) == 422, big
    assert report(attacker, replaced(("event", "end"), T - 1)) == 422  # before its start


def test_bodies_that_are_no_report_and_hostile_ids(attacker: Attacker) -> None:
    for content in (b"", b"{", b"null", b"[" * 50_000 + b"]" * 50_000, b"\xff\xfe", b'{"pull_id": NaN}'):
        answer = attacker.send("POST", f"/v1/runs/{RUN}/triggered", content=content)
        assert answer.status_code in (400, 415, 422), content[:40]
    for run in ("no-such-run", "..%2F..%2Fetc", "a" * 5000, "%00"):
        assert report(attacker, REPORT, run) in (404, 422), run
    for event in ("ev-0000000000000000", "..%2F", "x" * 5000, "%00", "ev-' OR 1=1 --"):
        status = attacker.send("POST", f"/v1/events/{event}/pull").status_code
        assert status in (404, 409, 422), event


@FUZZ
@given(
    changes=st.dictionaries(
        st.sampled_from(["pull_id", "priority", "state", "error", "rules_version", "chunks_sent"]),
        st.one_of(st.text(max_size=60), st.integers(), st.none(), st.booleans(), st.floats()),
        max_size=4,
    ),
    kind=st.text(max_size=80),
    include=st.lists(st.text(max_size=40), max_size=4),
)
def test_any_report_is_filed_or_refused(
    attacker: Attacker, changes: dict[str, Any], kind: str, include: list[str]
) -> None:
    body = replaced(("event", "kind"), kind)
    body["window"]["include"] = include
    body.update(changes)
    assert report(attacker, body) in (200, 201, 404, 409, 422)
