"""`PUT /v1/rules`, `GET /v1/rules`, `GET /v1/rules/history` with auth on, through the REST client:
a file checked whole, versions kept with who applied them and when, the running set untouched by a
bad file."""

from __future__ import annotations

import datetime as dt

from tests.services.auth.conftest import Depot, bearer
from tests.services.corpus.conftest import refused, sdk

RULES = """\
[[event]]
name = "intervention"
entity = "/autonomy/engaged"
when = "falls_below"
threshold = 0.5
severity = "warn"

[[metric]]
name = "distance_m"
kind = "path_length"
entity = "/world/robot"
"""

MORE = (
    RULES
    + """
[[metric]]
name = "interventions"
kind = "event_count"
event = "intervention"
"""
)

# Three problems on three lines: an unknown key, a condition that is none, a metric kind that is none.
BAD = """\
[[event]]
name = "stuck"
entity = "/logs/**"
when = "sometimes"
colour = "red"

[[metric]]
name = "m"
kind = "median"
entity = "/x"
"""


def test_rules_are_applied_versioned_and_shown(depot: Depot):
    alice = sdk(depot, depot.token("write", name="alice"))
    reader = sdk(depot, depot.token("read", name="rita"))
    empty = reader.rules()
    assert (empty["version"], empty["text"], empty["created_by"]) == (None, "", None)
    assert empty["rules"] == {"events": [], "metrics": [], "triggers": []}
    assert reader.rules_history() == []

    first = alice.apply_rules(RULES)
    assert (first["version"], first["changed"], first["created_by"]) == (1, True, "alice")
    assert [r["name"] for r in first["rules"]["events"]] == ["intervention"]
    event_rule = first["rules"]["events"][0]
    assert (event_rule["when"], event_rule["threshold"], event_rule["severity"], event_rule["line"]) == (
        "falls_below",
        0.5,
        "warn",
        1,
    )
    again = alice.apply_rules(RULES)  # the same text: no new version
    assert (again["version"], again["changed"]) == (1, False)
    bob = sdk(depot, depot.token("admin", name="bob"))
    second = bob.apply_rules(MORE)
    assert (second["version"], second["created_by"]) == (2, "bob")

    current = reader.rules()
    assert (current["version"], current["text"], current["created_by"]) == (2, MORE, "bob")
    assert [m["name"] for m in current["rules"]["metrics"]] == ["distance_m", "interventions"]
    history = reader.rules_history()
    assert [(v["version"], v["created_by"]) for v in history] == [(2, "bob"), (1, "alice")]
    for v in history:
        at = dt.datetime.fromisoformat(v["created_at"].replace("Z", "+00:00"))
        assert abs(dt.datetime.now(dt.UTC) - at) < dt.timedelta(minutes=5)
    older = reader.rules(1)
    assert (older["version"], older["text"], older["created_by"]) == (1, RULES, "alice")
    refused(lambda: reader.rules(7), 404, "no rules version 7")


def test_a_bad_file_is_refused_whole_with_every_problem_and_the_running_set_stays(depot: Depot):
    alice = sdk(depot, depot.token("write", name="alice"))
    alice.apply_rules(RULES)
    error = refused(lambda: alice.apply_rules(BAD), 422, "3 problem(s)", "nothing was applied")
    problems = {(p["line"], p["field"].rsplit(".", 1)[-1]) for p in error.body["problems"]}
    assert problems == {(4, "when"), (5, "colour"), (9, "kind")}, error.body["problems"]
    assert all(p["message"] for p in error.body["problems"])
    refused(lambda: alice.apply_rules("[[event]\nname = 1"), 422, "line 1")  # not TOML at all
    current = alice.rules()
    assert (current["version"], current["text"]) == (1, RULES)
    assert [v["version"] for v in alice.rules_history()] == [1]


def test_the_body_is_the_toml_file(depot: Depot):
    token = depot.token("write", name="alice")
    as_text = depot.client.put("/v1/rules", content=RULES, headers={**bearer(token), "Content-Type": "text/plain"})
    assert as_text.status_code == 200 and as_text.json()["version"] == 1
    as_json = depot.client.put("/v1/rules", json={"text": RULES}, headers=bearer(token))
    assert as_json.status_code == 422 and "content-type" in as_json.json()["message"]
    not_utf8 = depot.client.put(
        "/v1/rules", content=b"\xff\xfe", headers={**bearer(token), "Content-Type": "application/toml"}
    )
    assert not_utf8.status_code == 422 and "UTF-8" in not_utf8.json()["message"]
    too_big = depot.client.put(
        "/v1/rules", content=b"#" * (3 * 1024 * 1024), headers={**bearer(token), "Content-Type": "text/plain"}
    )
    assert too_big.status_code == 422
    assert depot.client.get("/v1/rules", headers=bearer(token)).json()["version"] == 1


def test_applying_needs_write_and_reading_needs_read_or_a_robots_token(depot: Depot):
    reader = sdk(depot, depot.token("read"))
    refused(lambda: reader.apply_rules(RULES), 403, "needs the 'write' scope")
    sdk(depot, depot.token("write")).apply_rules(RULES)
    robot = sdk(depot, depot.token("ingest", robot="robot-7"))
    assert robot.rules() == reader.rules()  # a robot's agent reads the rules it evaluates
    assert robot.rules(version=1)["version"] == 1
    refused(lambda: robot.rules(version=2), 404, "no rules version 2")
    refused(lambda: robot.apply_rules(MORE), 403, "needs the 'write' scope")
    refused(lambda: robot.rules_history(), 403, "needs the 'read' scope")
    for method, path in (("PUT", "/v1/rules"), ("GET", "/v1/rules"), ("GET", "/v1/rules/history")):
        assert depot.client.request(method, path, content=RULES).status_code == 401


def test_two_applies_at_once_one_is_told_to_apply_again(depot: Depot, monkeypatch):
    """Both read the same running version and take the next number: the second to commit is a 409
    saying to apply again, and the first one's version stands."""
    alice = sdk(depot, depot.token("write", name="alice"))
    alice.apply_rules(RULES)
    from catalog import corpus

    monkeypatch.setattr(corpus, "current_rules", lambda session: None)  # it has not seen version 1
    refused(lambda: alice.apply_rules(MORE), 409, "apply yours again")
    monkeypatch.undo()
    assert [v["version"] for v in alice.rules_history()] == [1]


def test_triggers_are_checked_with_the_file_and_shown(depot: Depot):
    alice = sdk(depot, depot.token("write", name="alice"))
    trigger = '\n[[trigger]]\nevent = "intervention"\ninclude = ["/camera/**"]\nbefore_s = 10\nafter_s = 5\n'
    applied = alice.apply_rules(RULES + trigger)
    assert applied["rules"]["triggers"] == [
        {
            "events": ["intervention"],
            "include": ["/camera/**"],
            "before_s": 10.0,
            "after_s": 5.0,
            "max_bytes_per_robot_day": None,
            "priority": "normal",
            "line": 13,
        }
    ]
    unknown = trigger.replace('"intervention"', '"hard_brake"')
    refused(lambda: alice.apply_rules(RULES + unknown), 422, "trigger[1].event", "'hard_brake'", "intervention")
    assert alice.rules()["version"] == applied["version"]  # the running set stays
