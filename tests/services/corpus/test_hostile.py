"""Hostile input to the corpus's routes (auth on, on each catalog): wrong types, huge bodies, control
characters and NUL bytes, SQL-ish text, path traversal, out-of-range and non-finite numbers, empty
bodies, wrong content types, deeply nested and enormous rules files, pathological regexes, tampered
cursors, and strings made up by hypothesis for the filters and the rules text.

Every answer is 2xx or 4xx, never 5xx; every 4xx carries a code and a message naming the problem;
and afterwards the depot still answers and what it had accepted before is there, unchanged."""

from __future__ import annotations

import base64
import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.console.app import install
from services.rules import spec
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.console.test_sessions import log_in
from tests.services.corpus.conftest import T0, add_run

RUN = "run-a"
RULES = """\
[[event]]
name = "intervention"
entity = "/autonomy/engaged"
when = "falls_below"
threshold = 0.5

[[metric]]
name = "distance_m"
kind = "path_length"
entity = "/world/robot"
"""
HOOK_URL = "http://127.0.0.1:9/hook"
CSRF = re.compile(r'name="csrf" value="([^"]+)"')
FUZZ = settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
HOSTILE_TEXTS = [
    "",
    " ",
    "\x00",
    "a\x00b",
    "\x1b[31mred\x1b[0m",
    "\r\n\t\x7f",
    "\u202egnp.exe",  # right-to-left override
    "\ufeff",
    "🤖" * 50,
    "x" * 5000,
    "'; DROP TABLE runs; --",
    "' OR '1'='1",
    '" OR 1=1 --',
    "%",
    "_",
    "\\",
    "../../../etc/passwd",
    "..%2F..%2Fetc%2Fpasswd",
    "${jndi:ldap://x}",
    "{{7*7}}",
    "<script>alert(1)</script>",
]
JSON_TEXTS = [*HOSTILE_TEXTS, "\ud800", "a\udfffb"]  # unpaired surrogates: JSON can carry them ("\\ud800")
BIG = [str(2**63), str(-(2**63) - 1), str(2**64), str(10**400), "-0", "1e309", "NaN", "Infinity", "-Infinity"]


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    """A depot with the console, webhooks allowed to one loopback host, a run, a rules version, a
    person's event, two tags and a webhook: what must be intact after every attack."""
    with open_depot(tmp_path, fresh_catalog_url, webhook_hosts=["127.0.0.1:9"]) as opened:
        install(opened.app)
        add_run(opened, RUN)
        writer, admin = bearer(opened.token("write", name="alice")), bearer(opened.token("admin"))
        put = opened.client.put("/v1/rules", content=RULES, headers={**writer, "content-type": "application/toml"})
        assert put.status_code == 200, put.text
        made = opened.client.post(
            f"/v1/runs/{RUN}/events",
            json={"timeline": "log_time", "start": T0, "end": T0 + 10, "label": "held"},
            headers=writer,
        )
        assert made.status_code == 200, made.text
        tagged = opened.client.post(f"/v1/runs/{RUN}/tags", json={"tags": ["night-shift", "dock-2"]}, headers=writer)
        assert tagged.status_code == 200, tagged.text
        hook = opened.client.post("/v1/webhooks", json={"url": HOOK_URL, "on": ["run.sealed"]}, headers=admin)
        assert hook.status_code == 201, hook.text
        yield opened


class Attacker:
    """Sends requests with a token of every scope and checks each answer: never a 5xx, and a 4xx
    with a code and a message."""

    def __init__(self, depot: Depot) -> None:
        self.depot = depot
        self.http = TestClient(depot.app, raise_server_exceptions=False)
        self.headers = bearer(depot.token("read", "write", "admin", name="mallory"))

    def send(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        headers = {**self.headers, **kwargs.pop("headers", {})}
        if "json" in kwargs:  # as JSON escapes: an unpaired surrogate goes as "\ud800", as clients send it
            kwargs["content"] = json.dumps(kwargs.pop("json")).encode()
            headers.setdefault("content-type", "application/json")
        answer: httpx.Response = self.http.request(method, url, headers=headers, **kwargs)
        assert answer.status_code < 500, f"{method} {url[:200]}: {answer.status_code} {answer.text[:2000]}"
        if answer.status_code >= 400:
            body = answer.json()
            assert body.get("code") and body.get("message"), f"{method} {url[:200]}: {answer.text[:500]}"
        return answer

    def refused(self, method: str, url: str, *says: str, status: int | None = None, **kwargs: Any) -> str:
        answer = self.send(method, url, **kwargs)
        assert 400 <= answer.status_code < 500, f"{method} {url[:200]} was accepted: {answer.text[:500]}"
        if status is not None:
            assert answer.status_code == status, answer.text[:500]
        message: str = answer.json()["message"]
        for text in says:
            assert text in message, message[:1000]
        return message

    def rules(self, text: str | bytes, content_type: str = "application/toml") -> httpx.Response:
        return self.send("PUT", "/v1/rules", content=text, headers={"content-type": content_type})


@pytest.fixture
def attacker(depot: Depot) -> Iterator[Attacker]:
    found = Attacker(depot)
    yield found
    assert_intact(found)


def assert_intact(attacker: Attacker) -> None:
    """The catalog answers and what was accepted before the attack is unchanged."""
    send = attacker.send
    assert send("GET", "/v1/rules").json()["text"] == RULES  # a fuzzed file that was accepted is put back
    assert send("GET", "/v1/rules", params={"version": 1}).json()["text"] == RULES
    assert send("GET", "/v1/rules/history").json()["versions"][-1]["version"] == 1
    events = send("GET", f"/v1/runs/{RUN}/events").json()["events"]
    held = [(e["id"], e["start"], e["end"], e["source"]) for e in events if e["label"] == "held"]
    assert [h[1:] for h in held] == [(T0, T0 + 10, "alice")]
    listed = send("GET", "/v1/events", params={"limit": 1000, "source": "alice"}).json()["events"]
    assert [e["id"] for e in listed] == [held[0][0]]
    run = send("GET", f"/v1/runs/{RUN}").json()
    assert sorted(t["tag"] for t in run["tags"]) == ["dock-2", "night-shift"], run
    found = send("GET", "/v1/runs", params={"tag": "night-shift"}).json()
    assert [r["id"] for r in found["runs"]] == [RUN]
    hooks = send("GET", "/v1/webhooks").json()["webhooks"]
    assert [(h["url"], h["on"]) for h in hooks] == [(HOOK_URL, ["run.sealed"])]


def cursor_of(value: Any) -> str:
    return base64.urlsafe_b64encode(json.dumps(value).encode()).decode().rstrip("=")


def raw_cursor(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


TAMPERED_CURSORS = [
    "",
    "!!!",
    "x" * 600,
    raw_cursor(b"\xff\xfe"),
    raw_cursor(b"[" * 10_000 + b"]" * 10_000),
    cursor_of(None),
    cursor_of([]),
    cursor_of([1, 2, 3]),
    cursor_of(["2026-01-01T00:00:00+00:00"]),
    cursor_of(["2026-01-01T00:00:00+00:00", None]),
    cursor_of(["2026-01-01T00:00:00+00:00", 5]),
    cursor_of(["2026-01-01T00:00:00+00:00", "ev-\x00"]),
    cursor_of(["2026-01-01T00:00:00", "ev-1"]),  # no zone
    cursor_of(["0001-01-01T00:00:00+14:00", "ev-1"]),
    cursor_of(["9999-12-31T23:59:59-14:00", "ev-1"]),
    cursor_of(["not a time", "ev-1"]),
    cursor_of([{"a": 1}, "ev-1"]),
    cursor_of([2**70, "run-a"]),
    cursor_of([-(2**70), "run-a"]),
    cursor_of([True, "run-a"]),
    cursor_of(["' OR 1=1 --", "run-a"]),
    base64.urlsafe_b64encode(b'[NaN, "run-a"]').decode(),
    base64.urlsafe_b64encode(b'[Infinity, "run-a"]').decode(),
    base64.urlsafe_b64encode(b'[1e999, "run-a"]').decode(),
    base64.urlsafe_b64encode(b"[" + b"9" * 500 + b', "run-a"]').decode(),
]


# --- the rules file ---------------------------------------------------------------------------------


def test_rules_bodies_of_the_wrong_kind_are_refused(attacker: Attacker) -> None:
    attacker.refused("PUT", "/v1/rules", "content-type", content=RULES, headers={"content-type": "application/json"})
    attacker.refused("PUT", "/v1/rules", "content-type", content=RULES)
    assert attacker.rules(b"\xff\xfe\x00garbage").status_code == 422
    attacker.refused("PUT", "/v1/rules", "UTF-8", content=b"\xc3\x28", headers={"content-type": "text/plain"})
    for text in ("x = \x00", '[[event]]\nname = "\x00"', "\x1b[2J", "[[event]", "= = =", "[[event]]\nname = 'a\nb'"):
        assert attacker.rules(text).status_code == 422, text


def test_a_50_mb_rules_file_is_refused_naming_the_limit(attacker: Attacker) -> None:
    body = b"# " + b"x" * (50 * 1024 * 1024)
    message = attacker.refused("PUT", "/v1/rules", content=body, headers={"content-type": "text/plain"})
    assert "bytes" in message


def test_rules_files_too_big_or_too_deep_are_refused_naming_the_limit(attacker: Attacker) -> None:
    cases = {
        "nested arrays": "x = " + "[" * 100_000 + "]" * 100_000,
        "nested inline tables": "x = " + "{a=" * 50_000 + "1" + "}" * 50_000,
        "a deep dotted key": "x" + ".x" * 200_000 + " = 1",
        "a deep table header": "[x" + ".x" * 200_000 + "]",
        "a deep inline key": "y = {x" + ".x" * 200_000 + " = 1}",
        "deep dotted keys on many lines": "".join(f"b{i}" + ".a" * 500 + " = 1\n" for i in range(400)),
        "100,000 rules": "[[event]]\n" * 100_000,
        "100,000 metrics": "[[metric]]\n" * 100_000,
        "90,000 unknown keys": "[[event]]\n" + "".join(f"k{i} = 1\n" for i in range(90_000)),
        "1,000 bad tables": "".join(f"[[metric]]\nzz{i} = 1\n" for i in range(1000)) + "\n" * 200_000,
    }
    for what, text in cases.items():
        answer = attacker.rules(text)
        assert answer.status_code in (413, 422), what
        body = answer.json()
        assert len(answer.content) < 64 * 1024, f"{what}: an answer of {len(answer.content)} bytes"
        assert body["problems"] if answer.status_code == 422 else body["message"], what
    said = {what: attacker.rules(text).json()["message"] for what, text in cases.items()}
    assert f"more than {spec.MAX_KEY_PARTS} parts" in said["a deep dotted key"]
    assert "nested too deeply" in said["nested arrays"]
    assert f"100000 tables: at most {spec.MAX_RULES}" in said["100,000 rules"]
    assert f"not listed: at most {spec.MAX_PROBLEMS}" in said["90,000 unknown keys"]


def test_a_thousand_rules_are_read_and_a_thousand_and_one_refused(attacker: Attacker, depot: Depot) -> None:
    def rules(count: int) -> str:
        return "".join(f'[[metric]]\nname = "m{i}"\nkind = "property"\nproperty = "fleet.x{i}"\n' for i in range(count))

    attacker.refused("PUT", "/v1/rules", f"at most {spec.MAX_RULES}", content=rules(spec.MAX_RULES + 1),
                     headers={"content-type": "text/plain"})  # fmt: skip
    # A file at the limit is checked (not applied: the depot's file must stay as it was).
    spec.parse_rules(rules(spec.MAX_RULES))


def test_huge_and_pathological_regexes_are_refused_or_harmless(attacker: Attacker) -> None:
    def text_rule(match: str) -> str:
        return f'[[event]]\nname = "stuck"\nentity = "/logs/**"\nwhen = "text"\nmatch = {json.dumps(match)}\n'

    for match in ("(a)\\1", "(?=a)b", "(?<!a)b", "a{1001}", "((a{100}){100}){100}", "x" * (spec.MAX_REGEX_LENGTH + 1),
                  "[", "(?P<n>a)(?P=n)", "\\p{NoSuchClass}"):  # fmt: skip
        message = attacker.refused("PUT", "/v1/rules", "match", content=text_rule(match),
                                   headers={"content-type": "text/plain"})  # fmt: skip
        assert len(message) < 4000
    for harmless in ("(a+)+$", "(a|a)*b", "(.*a){20}", "(?i)stuck|blocked", "\x00"):
        rules = spec.parse_rules(text_rule(harmless))
        assert rules.events[0].pattern.search("a" * 100_000 + "!") is None or harmless in ("(.*a){20}",)


def test_rules_values_of_every_wrong_type_are_named(attacker: Attacker) -> None:
    for value in ("1", "true", "[1, 2]", "{a = 1}", "1979-05-27T07:32:00Z", "nan", "inf", "-inf", "1e400",
                  "9223372036854775808", '"' + "x" * 100_000 + '"'):  # fmt: skip
        for key in ("name", "entity", "when", "threshold", "for_s", "severity", "timeline"):
            lines = ['name = "e"', 'entity = "/a"', 'when = "above"', "threshold = 1"]
            text = "[[event]]\n" + "\n".join(line for line in lines if not line.startswith(f"{key} = ")) + "\n"
            text += f"{key} = {value}\n"
            answer = attacker.rules(text)
            if answer.status_code == 200:  # a value of the right type after all (threshold = 1): put back
                assert attacker.rules(RULES).status_code == 200
                continue
            message = answer.json()["message"]
            assert "event[1]" in message or "toml" in message, message[:300]
            assert len(message) < 4000, f"{key} = {value[:20]}: a message of {len(message)} characters"


@FUZZ
@given(text=st.text(max_size=400))
def test_any_text_as_a_rules_file_is_read_or_refused(attacker: Attacker, text: str) -> None:
    answer = attacker.rules(text.encode("utf-8", "surrogatepass"))
    assert answer.status_code in (200, 422)
    if answer.status_code == 200:  # blank or comments only: an empty rule set; put the depot's file back
        assert answer.json()["rules"] == {"events": [], "metrics": [], "triggers": []}
        assert attacker.rules(RULES).status_code == 200


TOML_SCALAR = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70).map(str),
    st.floats().map(
        lambda f: "nan" if f != f else "inf" if f == float("inf") else "-inf" if f == -float("inf") else repr(f)
    ),
    st.booleans().map(lambda b: "true" if b else "false"),
    st.text(max_size=40).map(json.dumps),
    st.sampled_from(['"/a/**"', '"/**"', '"falls_below"', '"text"', '"ERROR"', '"(?i)x"', '"path_length"', "[]", "{}"]),
)
TOML_KEY = st.sampled_from([*spec._EVENT_KEYS, *spec._METRIC_KEYS, "colour", '"na\\u0000me"'])


@FUZZ
@given(
    tables=st.lists(
        st.tuples(
            st.sampled_from(["event", "metric", "trigger", "other"]),
            st.dictionaries(TOML_KEY, TOML_SCALAR, max_size=8),
        ),
        max_size=6,
    )
)
def test_any_rules_made_of_tables_are_read_or_refused(
    attacker: Attacker, tables: list[tuple[str, dict[str, str]]]
) -> None:
    text = "".join(f"[[{kind}]]\n" + "".join(f"{k} = {v}\n" for k, v in values.items()) for kind, values in tables)
    answer = attacker.rules(text.encode("utf-8", "surrogatepass"))
    assert answer.status_code in (200, 422)
    if answer.status_code == 200:  # put the depot's file back
        assert attacker.rules(RULES).status_code == 200


def test_rules_versions_out_of_range_are_refused(attacker: Attacker) -> None:
    for version in ("0", "-1", "abc", "1.5", str(2**31), str(2**63), str(2**64), str(10**400), "NaN", "\x00"):
        attacker.refused("GET", "/v1/rules", "version", params={"version": version})
    attacker.refused("GET", "/v1/rules", params={"version": "2"}, status=404)


# --- events -----------------------------------------------------------------------------------------


def test_event_filters_with_hostile_values_answer_or_are_refused(attacker: Attacker) -> None:
    for value in HOSTILE_TEXTS:
        for name in ("kind", "robot", "run", "source", "severity", "origin"):
            attacker.send("GET", "/v1/events", params={name: value})
    for name in ("since", "until"):
        for value in ("0001-01-01T00:00:00+14:00", "9999-12-31T23:59:59-14:00", "2026-13-45", "\x00", "9" * 100, ""):
            attacker.send("GET", "/v1/events", params={name: value})
    for limit in ("0", "-1", "1001", str(2**63), str(10**400), "NaN", "1e3", "abc"):
        attacker.refused("GET", "/v1/events", "limit", params={"limit": limit})
    attacker.refused("GET", "/v1/events", "at most", params=[("kind", str(i)) for i in range(100)])


def cursor_answered(attacker: Attacker, url: str, params: dict[str, str]) -> None:
    """A tampered cursor is refused naming it, or (when it is well formed) read as a place to start."""
    answer = attacker.send("GET", url, params=params)
    assert answer.status_code in (200, 422), f"{params}: {answer.status_code}"
    if answer.status_code == 422:
        assert "cursor" in answer.json()["message"]


def test_tampered_event_cursors_are_422(attacker: Attacker) -> None:
    for cursor in TAMPERED_CURSORS:
        if cursor:
            cursor_answered(attacker, "/v1/events", {"cursor": cursor})


def test_hostile_event_and_run_ids_are_404_or_422(attacker: Attacker) -> None:
    for ident in [*HOSTILE_TEXTS[1:], "%2e%2e", "ev-" + "0" * 16, "ev-%00", "%00", "x" * 10_000]:
        path = quote(ident, safe="")
        for url in (f"/v1/events/{path}", f"/v1/runs/{path}/events"):
            answer = attacker.send("GET", url)
            assert answer.status_code in (404, 422), f"{url[:80]}: {answer.status_code}"
    for url in ("/v1/events/%00", "/v1/runs/%00/events", "/v1/events/..%2F..%2Fetc%2Fpasswd"):
        assert attacker.send("GET", url).status_code in (404, 422)


# --- annotations ------------------------------------------------------------------------------------


def annotate(attacker: Attacker, body: Any, run: str = RUN, **kwargs: Any) -> httpx.Response:
    if "content" in kwargs:
        return attacker.send("POST", f"/v1/runs/{run}/events", **kwargs)
    return attacker.send("POST", f"/v1/runs/{run}/events", json=body, **kwargs)


def test_annotations_of_every_wrong_shape_are_422(attacker: Attacker) -> None:
    base = {"timeline": "frame", "start": 1}
    bad_bodies: list[Any] = [
        None, [], "x", 1, {}, {"timeline": "frame"}, {"start": 1}, {**base, "start": 1.5}, {**base, "start": None},
        {**base, "start": [1]}, {**base, "start": {"a": 1}}, {**base, "start": True}, {**base, "end": False},
        {**base, "timeline": 5}, {**base, "label": 5}, {**base, "label": None}, {**base, "note": ["x"]},
        {**base, "severity": "fatal"}, {**base, "kind": ""}, {**base, "kind": "a b"}, {**base, "kind": "\x00"},
        {**base, "kind": "x" * 129}, {**base, "timeline": ""}, {**base, "timeline": "\x00"},
        {**base, "timeline": "x" * 100_000}, {**base, "extra": 1},
        {**base, "label": "x" * (1024 * 1024)}, {**base, "note": "x" * (1024 * 1024)},
    ]  # fmt: skip
    for body in bad_bodies:
        assert annotate(attacker, body).status_code == 422, str(body)[:200]
    starts: list[Any] = [*BIG, "", " ", "\x00", "1\x00", "0x10", "1_000", "--1", "1e3", "12.5s", "' OR 1=1 --"]
    for start in [*starts, 2**63, -(2**63) - 1, 2**64, 10**400]:
        for timeline in ("frame", "log_time"):
            answer = annotate(attacker, {"timeline": timeline, "start": start})
            if answer.status_code == 200:  # a value this timeline takes ("-0", "1e3" ns): a new event, unlabelled
                continue
            assert answer.status_code == 422, f"{timeline} {str(start)[:40]}: {answer.text[:300]}"
    for body in (b"", b"{", b"null", b"[" * 100_000 + b"]" * 100_000, b'{"timeline": "frame", "start": NaN}',
                 b'{"timeline": "frame", "start": Infinity}', b'{"timeline": "frame", "start": 1e999}',
                 b'{"timeline": "frame", "start": 1, "label": ' + b"[" * 50_000 + b"]" * 50_000 + b"}",
                 b"\xff\xfe", b'{"timeline": "frame", "start": 1, "label": "\\ud800"}'):  # fmt: skip
        for kind in ("application/json", "text/plain", "application/x-www-form-urlencoded", ""):
            answer = annotate(attacker, None, content=body, headers={"content-type": kind})
            assert answer.status_code in (400, 415, 422), f"{body[:40]!r} as {kind}: {answer.status_code}"


def test_annotation_text_with_control_characters_is_kept_or_refused_never_a_500(
    attacker: Attacker, depot: Depot
) -> None:
    for text in JSON_TEXTS:
        for field in ("label", "note", "timeline", "kind"):
            answer = annotate(attacker, {"timeline": "frame", "start": 1, field: text})
            assert answer.status_code in (200, 422), f"{field} {text[:20]!r}"
            if answer.status_code == 200:
                made = answer.json()
                assert made[field] == text
                shown = attacker.send("GET", f"/v1/events/{made['id']}").json()
                assert shown[field] == text


# --- tags -------------------------------------------------------------------------------------------


def test_tags_of_every_wrong_shape_are_422(attacker: Attacker) -> None:
    bad: list[Any] = [None, {}, [], {"tags": "x"}, {"tags": None}, {"tags": [1]}, {"tags": [None]}, {"tags": []},
                      {"tags": [""]}, {"tags": ["a b"]}, {"tags": ["a,b"]}, {"tags": ["\x00"]}, {"tags": ["a\x00"]},
                      {"tags": ["\x1b[31m"]}, {"tags": ["\u200b"]}, {"tags": ["x" * 129]},
                      {"tags": ["x" * 1024 * 1024]}, {"tags": [f"t{i}" for i in range(10_000)]},
                      {"tags": ["ok"], "extra": 1}]  # fmt: skip
    for body in bad:
        for method in ("POST", "DELETE"):
            answer = attacker.send(method, f"/v1/runs/{RUN}/tags", json=body)
            assert answer.status_code == 422, f"{method} {str(body)[:80]}: {answer.status_code}"
    many = attacker.refused("POST", f"/v1/runs/{RUN}/tags", "at most", json={"tags": [f"t{i}" for i in range(10_000)]})
    assert "10000" in many
    for raw in (b"", b"{", b"\xff", b"[" * 100_000 + b"]" * 100_000):
        for method in ("POST", "DELETE"):
            answer = attacker.send(
                method, f"/v1/runs/{RUN}/tags", content=raw, headers={"content-type": "application/json"}
            )
            assert answer.status_code in (400, 422), f"{method} {raw[:20]!r}: {answer.status_code}"
    for tag in ("\x00", "", "a b", "x" * 200):
        attacker.refused("DELETE", f"/v1/runs/{RUN}/tags", "tags", params={"tag": tag})
    for text in JSON_TEXTS:
        for method in ("POST", "DELETE"):
            answer = attacker.send(method, f"/v1/runs/{RUN}/tags", json={"tags": [text]})
            assert answer.status_code in (200, 422), f"{method} {text[:20]!r}"
            if answer.status_code == 200 and method == "POST":
                assert text in [t["tag"] for t in answer.json()["tags"]]


def test_tags_on_hostile_run_ids_are_404(attacker: Attacker) -> None:
    for run in ("%00", "..%2F..", "x" * 10_000, quote("' OR 1=1 --"), "%E2%80%AE", "run-a%00", "%2E%2E"):
        for method in ("POST", "DELETE"):
            answer = attacker.send(method, f"/v1/runs/{run}/tags", json={"tags": ["x"]})
            assert answer.status_code in (404, 422), f"{method} {run[:40]}"


def test_unicode_tags_are_kept_as_given(attacker: Attacker) -> None:
    for tag in ("nuit-🌙", "日本語", "ünïcödé", "a'b", '"q"', "%_", "--", "a;b"):
        added = attacker.send("POST", f"/v1/runs/{RUN}/tags", json={"tags": [tag]}).json()
        assert tag in [t["tag"] for t in added["tags"]]
        found = attacker.send("GET", "/v1/runs", params={"tag": tag}).json()["runs"]
        assert [r["id"] for r in found] == [RUN]
        removed = attacker.send("DELETE", f"/v1/runs/{RUN}/tags", params={"tag": tag}).json()
        assert removed["removed"] == [tag]


# --- finding runs -----------------------------------------------------------------------------------


def test_run_filters_with_hostile_values_answer_or_are_refused(attacker: Attacker) -> None:
    for value in [*HOSTILE_TEXTS, *BIG]:
        for name in ("tag", "event"):
            answer = attacker.send("GET", "/v1/runs", params={name: value})
            assert answer.status_code in (200, 422)
            if answer.status_code == 200:
                assert answer.json()["runs"] == []
        for expression in (value, f"distance_m>{value}", f"distance_m={value}", f"{value}>1", f"distance_m!={value}"):
            answer = attacker.send("GET", "/v1/runs", params={"metric": expression})
            assert answer.status_code in (200, 422), expression[:80]
        attacker.send("GET", "/v1/runs", params={"sort": f"metric.{value}"})
    for expression in ("distance_m>NaN", "distance_m<Infinity", "distance_m>=-Infinity", "distance_m>1e309", "x=>1",
                       "x>>1", ">1", "x>", "x", "distance_m>0x10", "distance_m>" + "9" * 5000):  # fmt: skip
        attacker.refused("GET", "/v1/runs", "metric", params={"metric": expression})
    attacker.refused("GET", "/v1/runs", "at most", params=[("tag", str(i)) for i in range(1000)])


def test_tampered_run_cursors_are_422_for_every_sort(attacker: Attacker) -> None:
    for sort in ("metric.distance_m", "-metric.distance_m", "-started_at", "bytes", "id"):
        for cursor in TAMPERED_CURSORS:
            if cursor:
                cursor_answered(attacker, "/v1/runs", {"sort": sort, "cursor": cursor})


METRIC_EXPRESSION = st.one_of(
    st.text(max_size=60),
    st.tuples(
        st.sampled_from(["distance_m", "sw_version", "x" * 128, "x" * 129, "é", ""]),
        st.sampled_from(
            ["", " ", *[f"{s}{op}{s}" for op in (">", ">=", "<", "<=", "=", "!=") for s in ("", " ")], "=>", "<>"]
        ),
        st.one_of(st.text(max_size=30), st.floats().map(repr), st.integers().map(str)),
    ).map("".join),
)


@FUZZ
@given(
    expressions=st.lists(METRIC_EXPRESSION, min_size=1, max_size=3), tag=st.text(max_size=30), sort=st.text(max_size=30)
)
def test_any_run_filter_is_answered_or_refused(attacker: Attacker, expressions: list[str], tag: str, sort: str) -> None:
    for params in (
        [("metric", e) for e in expressions],
        {"tag": tag, "event": tag},
        {"sort": sort},
        {"sort": "metric." + sort},
    ):
        assert attacker.send("GET", "/v1/runs", params=params).status_code in (200, 422)


EVENT_FILTERS = ["kind", "robot", "run", "source", "since", "until", "cursor", "severity"]


@FUZZ
@given(values=st.dictionaries(st.sampled_from(EVENT_FILTERS), st.text(max_size=40), max_size=4))
def test_any_event_filter_is_answered_or_refused(attacker: Attacker, values: dict[str, str]) -> None:
    assert attacker.send("GET", "/v1/events", params=values).status_code in (200, 422)


# --- webhooks -----------------------------------------------------------------------------------------


def test_webhooks_of_every_wrong_shape_are_refused(attacker: Attacker) -> None:
    bad: list[Any] = [
        None, [], {}, {"url": HOOK_URL}, {"on": ["run.sealed"]}, {"url": 5, "on": ["run.sealed"]},
        {"url": HOOK_URL, "on": "run.sealed"}, {"url": HOOK_URL, "on": []}, {"url": HOOK_URL, "on": [None]},
        {"url": HOOK_URL, "on": ["event:" + "x" * 300]}, {"url": HOOK_URL, "on": ["event:\x00"]},
        {"url": HOOK_URL, "on": [f"event:k{i}" for i in range(10_000)]},
        {"url": HOOK_URL, "on": ["run.sealed"], "format": "xml"}, {"url": HOOK_URL, "on": ["run.sealed"], "format": 1},
        {"url": "http://127.0.0.1:9/\x00", "on": ["run.sealed"]},
        {"url": "http://127.0.0.1:9/" + "x" * 1024 * 1024, "on": ["run.sealed"]},
        {"url": "file:///etc/passwd", "on": ["run.sealed"]}, {"url": "http://169.254.169.254/", "on": ["run.sealed"]},
        {"url": "http://user:pw@127.0.0.1:9/", "on": ["run.sealed"]},
        {"url": "http://[::1", "on": ["run.sealed"]}, {"url": "http://127.0.0.1:99999/", "on": ["run.sealed"]},
        {"url": "http://127.0.0.1:-1/", "on": ["run.sealed"]}, {"url": "http://\u202e.example/", "on": ["run.sealed"]},
        {"url": "http://127.0.0.1:9/\ud800", "on": ["run.sealed"]}, {"url": HOOK_URL, "on": ["event:\ud800"]},
    ]  # fmt: skip
    bad += [{"url": HOOK_URL, "on": [text]} for text in JSON_TEXTS]
    unsendable = [t for t in JSON_TEXTS if any(c.isspace() or ord(c) < 32 or 0xD800 <= ord(c) < 0xE000 for c in t)]
    bad += [{"url": HOOK_URL + text, "on": ["run.sealed"]} for text in unsendable]
    for body in bad:
        answer = attacker.send("POST", "/v1/webhooks", json=body)
        assert answer.status_code == 422, f"{str(body)[:120]}: {answer.status_code} {answer.text[:200]}"
        assert "secret" not in answer.json()


def test_hostile_webhook_ids_and_cursors_are_404_or_422(attacker: Attacker) -> None:
    hook = attacker.send("GET", "/v1/webhooks").json()["webhooks"][0]["id"]
    for ident in ("%00", "wh-%00", "..%2F..", "x" * 10_000, quote("' OR 1=1 --"), "%E2%80%AE", "%2E%2E"):
        for method, url in (("GET", f"/v1/webhooks/{ident}/deliveries"), ("DELETE", f"/v1/webhooks/{ident}")):
            assert attacker.send(method, url).status_code in (404, 422), f"{method} {url[:60]}"
    for cursor in TAMPERED_CURSORS:
        if cursor:
            cursor_answered(attacker, f"/v1/webhooks/{hook}/deliveries", {"cursor": cursor})
    for limit in ("0", "-1", str(2**63), str(10**400), "x"):
        attacker.refused("GET", f"/v1/webhooks/{hook}/deliveries", "limit", params={"limit": limit})


# --- the console --------------------------------------------------------------------------------------


def page_answered(page: httpx.Response, what: str) -> None:
    """A console page or form: shown, or a 4xx page (or JSON) saying what was wrong; never a 5xx."""
    assert page.status_code < 500, f"{what}: {page.status_code} {page.text[:500]}"
    if page.status_code >= 400 and page.status_code != 404:
        said = page.json()["message"] if "json" in page.headers["content-type"] else page.text
        assert "parameter" in said or "characters" in said or "tag" in said or "body" in said, f"{what}: {said[:500]}"


def browser(depot: Depot) -> TestClient:
    return log_in(TestClient(depot.app, raise_server_exceptions=False), depot.token("read", "write", name="mallory"))


def test_console_pages_take_hostile_parameters(depot: Depot, attacker: Attacker) -> None:
    client = browser(depot)
    for value in [*HOSTILE_TEXTS, *TAMPERED_CURSORS[::3], *BIG[::2]]:
        for name in ("kind", "robot", "severity", "source", "run", "cursor"):
            page_answered(client.get("/console/events", params={name: value}), f"events {name}={value[:40]!r}")
        for name in ("metric", "tag", "event", "sort", "cursor"):
            page_answered(client.get("/console/runs", params={name: value}), f"runs {name}={value[:40]!r}")


def test_the_dashboard_takes_hostile_metric_names(depot: Depot, attacker: Attacker) -> None:
    client = browser(depot)  # each look runs its SQL: a few of each kind of value
    for value in ("\x00", "' OR '1'='1", "x'; DROP TABLE runs; --", "a\\b", "x" * 5000, "🤖", "", "-1", "NaN"):
        for name in ("distance", "interventions", "version"):
            page = client.get("/console/dashboards/interventions", params={name: value})
            page_answered(page, f"dashboard {name}={value[:40]!r}")


def test_run_page_edit_forms_take_hostile_input(depot: Depot, attacker: Attacker) -> None:
    client = browser(depot)
    page = client.get(f"/console/runs/{RUN}")
    assert page.status_code == 200, page.text[:300]
    found = CSRF.search(page.text)
    assert found
    token = found.group(1)
    forms: list[tuple[str, dict[str, str]]] = []
    for value in [*HOSTILE_TEXTS, *BIG, "x" * (1024 * 1024)]:
        forms += [
            ("tags", {"tags": value}),
            ("tags/remove", {"tag": value}),
            ("annotate", {"timeline": "frame", "start": "1", "label": value}),
            ("annotate", {"timeline": "frame", "start": value}),
            ("annotate", {"timeline": "frame", "start": "1", "end": value}),
            ("annotate", {"timeline": value, "start": "1"}),
        ]
    forms.append(("tags", {"tags": " ".join(f"t{i}" for i in range(10_000))}))
    for path, data in forms:
        answer = client.post(f"/console/runs/{RUN}/{path}", data={"csrf": token, **data}, follow_redirects=False)
        page_answered(answer, f"{path} {str(data)[:80]}")
        if answer.status_code == 303 and path == "tags":  # accepted: take it away again
            for tag in [t for t in re.split(r"[\s,]+", data["tags"]) if t]:
                client.post(f"/console/runs/{RUN}/tags/remove", data={"csrf": token, "tag": tag})
    for run in ("%00", "..%2F..", "x" * 10_000):
        answer = client.post(f"/console/runs/{run}/tags", data={"csrf": token, "tags": "x"}, follow_redirects=False)
        assert answer.status_code in (404, 422), run[:40]
        page_answered(answer, run[:40])
